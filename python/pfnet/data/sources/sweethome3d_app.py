"""SweetHome3D's own default catalogue, read from the application's ``sweethome3d.jar``.

Debian's ``sweethome3d`` package installs ``/usr/share/sweethome3d/sweethome3d.jar``; inside
it, ``com/eteks/sweethome3d/io/DefaultFurnitureCatalog.properties`` lists the default models
(the same ``name#N=``, ``category#N=``, ``model#N=`` keys as a ``.sh3f`` catalogue) and
``com/eteks/sweethome3d/io/resources/`` holds their OBJ files: 93 models, none of them among
the 820 of ``sweethome3d-furniture``. The jar is a ZIP, read like a ``.sh3f``
(:mod:`pfnet.data.sources.sweethome3d`: the same keyword categories, light sources dropped,
``modelRotation`` applied; y-up, centimetres). Unmatched names get ``other``. Licence, from
the catalogue: "GNU GPL / CC-BY 3.0 © Emmanuel Puybaret / eTeks"; each model's creator is
credited.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

from pfnet.data.sources import Scan, ShapeItem, unique_names
from pfnet.data.sources.sweethome3d import catalogue_entries, read_catalogue

__all__ = ["CATALOGUE_MEMBER", "DEFAULT_PATH", "looks_like", "scan"]

DEFAULT_PATH = Path("/usr/share/sweethome3d/sweethome3d.jar")
"""Where Debian's ``sweethome3d`` package installs the application."""

CATALOGUE_MEMBER = "com/eteks/sweethome3d/io/DefaultFurnitureCatalog.properties"


def _jar(source: Path) -> Path:
    return source / "sweethome3d.jar" if source.is_dir() else source


def looks_like(source: Path) -> bool:
    """Whether ``source`` is ``sweethome3d.jar`` or a folder holding it."""
    jar = _jar(source)
    if not jar.is_file() or jar.suffix.lower() != ".jar":
        return False
    try:
        with zipfile.ZipFile(jar) as archive:
            archive.getinfo(CATALOGUE_MEMBER)
    except (KeyError, OSError, zipfile.BadZipFile):
        return False
    return True


def scan(source: Path) -> Scan:
    """Read the default catalogue of the SweetHome3D application.

    Args:
        source: ``sweethome3d.jar`` or the folder holding it (``/usr/share/sweethome3d``).

    Returns:
        The scan: one item per catalogue model (kind ``sh3f``: the jar is a ZIP like a
        catalogue), creators credited, light sources counted as dropped.

    Raises:
        DataError: No jar, or no default catalogue in it.
    """
    jar = _jar(source)
    properties = read_catalogue(
        jar,
        CATALOGUE_MEMBER,
        missing=f"no {CATALOGUE_MEMBER} (not the SweetHome3D application)",
        unreadable="cannot read the application's catalogue",
    )
    dropped = {"light_source": 0}
    credits: dict[str, tuple[str, str]] = {}
    pending = catalogue_entries(jar, properties, dropped, credits)
    names = unique_names({key: f"sh3d-app_{stem}" for key, stem, *_ in pending})
    items = [
        ShapeItem(key=key, name=names[key], category=category, path=display, kind="sh3f", args=args)
        for key, _, category, display, args in pending
    ]
    licenses = [
        {
            "source": jar.name,
            "catalogue": properties.get("name", "SweetHome3D default catalogue"),
            "license": properties.get("license", "GPL-2+"),
            "provider": properties.get("provider", "www.sweethome3d.com"),
        }
    ]
    return Scan(items=items, licenses=licenses, dropped=dropped, credits=credits)
