"""TORCS' cars: ``cars/<car>/<car>.acc`` of a TORCS data tree.

Debian's ``torcs-data`` installs ``/usr/share/games/torcs`` with 17 cars, each a folder holding
the full-detail model ``<car>.acc`` and lower levels of detail ``<car>-lod1.acc``... Only the
full-detail file is read (a car folder without one is reported as skipped); the level-of-detail
files, the ``wheels`` (separate wheel meshes) and the ``tracks`` (whole circuits, not objects)
are left out and counted. ``.acc`` is AC3D with TORCS' own additions (triangle strips,
normals, four texture layers), read by :mod:`pfnet.io.formats.ac3d`; the files are y-up (see
:mod:`pfnet.data.sources.ac3d_trees`). Licence: Free Art License for the cars
(``/usr/share/doc/torcs-data/copyright``).
"""

from __future__ import annotations

import re
from pathlib import Path

from pfnet.data.sources import Scan
from pfnet.data.sources.ac3d_trees import Found, make_scan
from pfnet.errors import DataError

__all__ = ["DEFAULT_PATH", "looks_like", "scan"]

DEFAULT_PATH = Path("/usr/share/games/torcs")
"""Where Debian's ``torcs-data`` installs the data tree."""

LICENSE = {
    "source": "torcs",
    "catalogue": "TORCS cars (torcs-data)",
    "license": "Free Art License (see /usr/share/doc/torcs-data/copyright)",
    "provider": "The TORCS project, torcs.sourceforge.net",
}

_LOD = re.compile(r"-lod\d+$", re.IGNORECASE)


def looks_like(source: Path) -> bool:
    """Whether ``source`` is a TORCS data tree (``cars/<car>/<car>.acc``)."""
    return source.is_dir() and (source / "cars").is_dir() and any(source.glob("cars/*/*.acc"))


def scan(source: Path) -> Scan:
    """Find the cars of a TORCS data tree.

    Args:
        source: The data tree (holding ``cars/``).

    Returns:
        The scan: one ``car`` per car folder's full-detail model; level-of-detail files,
        wheels and tracks counted as dropped.

    Raises:
        DataError: No ``cars`` folder, or no car in it.
    """
    if not looks_like(source):
        raise DataError(f"{source}: not a TORCS data tree (no cars/<car>/<car>.acc)")
    found: list[Found] = []
    for path in sorted(source.rglob("*")):
        if path.suffix.lower() not in (".acc", ".ac") or not path.is_file():
            continue
        relative = path.relative_to(source).as_posix()
        parts = relative.split("/")
        if parts[0] == "cars" and len(parts) == 3:
            if _LOD.search(path.stem):
                found.append(Found(path, relative, None, "level_of_detail"))
            elif path.stem == parts[1]:
                found.append(Found(path, relative, "car", ""))
            else:
                found.append(Found(path, relative, None, "car_part"))
        else:
            reason = {"tracks": "track", "wheels": "wheel"}.get(parts[0], "not_a_car")
            found.append(Found(path, relative, None, reason))
    return make_scan("torcs", found, [LICENSE])
