"""crrcsim's radio-controlled aircraft: the models its ``models/*.xml`` files name.

Debian's ``crrcsim-data`` installs ``/usr/share/games/crrcsim``: ``objects/*.ac`` holds the
aircraft and the scenery's props (trees, huts, a table, the terrain), and each
``models/<model>.xml`` names its aircraft's ``.ac`` file. Only the files an XML names are read
(26 planes and gliders, 3 helicopters: ``heli``/``copter`` in the name); the props are counted
as dropped. The files are y-up (see :mod:`pfnet.data.sources.ac3d_trees`). Licence: GPL-2
(``/usr/share/doc/crrcsim-data/copyright``).
"""

from __future__ import annotations

import re
from pathlib import Path

from pfnet.data.sources import Scan
from pfnet.data.sources.ac3d_trees import Found, make_scan
from pfnet.errors import DataError

__all__ = ["DEFAULT_PATH", "looks_like", "scan"]

DEFAULT_PATH = Path("/usr/share/games/crrcsim")
"""Where Debian's ``crrcsim-data`` installs the data tree."""

LICENSE = {
    "source": "crrcsim",
    "catalogue": "crrcsim model aircraft (crrcsim-data)",
    "license": "GPL-2",
    "provider": "The CRRCsim project, sourceforge.net/projects/crrcsim",
}

_REFERENCE = re.compile(rb"([\w.+-]+\.ac)\b", re.IGNORECASE)
_HELICOPTER = re.compile(r"heli|copter", re.IGNORECASE)
MAX_XML_BYTES = 4 << 20


def looks_like(source: Path) -> bool:
    """Whether ``source`` is a crrcsim data tree (``models/*.xml`` and ``objects/*.ac``)."""
    return source.is_dir() and any(source.glob("models/*.xml")) and any(source.glob("objects/*.ac"))


def scan(source: Path) -> Scan:
    """Find the aircraft of a crrcsim data tree.

    Raises:
        DataError: Not a crrcsim tree, or no model names an existing ``.ac`` file.
    """
    if not looks_like(source):
        raise DataError(f"{source}: not a crrcsim data tree (no models/*.xml and objects/*.ac)")
    named: set[str] = set()
    for xml in sorted(source.glob("models/*.xml")):
        with open(xml, "rb") as fh:
            named |= {m.decode().lower() for m in _REFERENCE.findall(fh.read(MAX_XML_BYTES))}
    found: list[Found] = []
    for path in sorted(source.glob("objects/*.ac")):
        relative = path.relative_to(source).as_posix()
        if path.name.lower() in named:
            category = "helicopter" if _HELICOPTER.search(path.stem) else "airplane"
            found.append(Found(path, relative, category))
        else:
            found.append(Found(path, relative, None, "scenery_prop"))
    return make_scan("crrcsim", found, [LICENSE])
