"""ShapeNet-Part (``shapenetcore_partanno_segmentation_benchmark_v0``), the paper's data.

Layout::

    ROOT/synsetoffset2category.txt                      "<Category>\\t<synset>" per line
    ROOT/<synset>/points/<id>.pts                       whitespace x y z per line
    ROOT/train_test_split/shuffled_{train,val,test}_file_list.json
                                                        ["shape_data/<synset>/<id>", ...]

The dataset's own split lists are used; shapes in no list are left out (as the authors'
loader does). Category names are the lower-cased first column (``airplane``, ``chair``...).
Each ``.pts`` cloud (about 2,500 points) is resampled to the point count (IFPS).
"""

from __future__ import annotations

import json
from pathlib import Path

from pfnet.data.sources import Scan, ShapeItem, safe_name
from pfnet.errors import DataError

__all__ = ["CATEGORY_FILE", "looks_like", "scan"]

CATEGORY_FILE = "synsetoffset2category.txt"
_SPLIT_FILES = {split: f"shuffled_{split}_file_list.json" for split in ("train", "val", "test")}


def looks_like(root: Path) -> bool:
    """Whether ``root`` holds ``synsetoffset2category.txt``."""
    return (root / CATEGORY_FILE).is_file()


def _categories(root: Path) -> dict[str, str]:
    path = root / CATEGORY_FILE
    synsets: dict[str, str] = {}
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as err:
        raise DataError(f"{path}: cannot read: {err}") from err
    for number, line in enumerate(lines, 1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) != 2:
            raise DataError(f"{path}:{number}: expected '<Category> <synset>', got {line!r}")
        synsets[fields[1]] = safe_name(fields[0])
    if not synsets:
        raise DataError(f"{path}: lists no categories")
    return synsets


def scan(root: Path) -> Scan:
    """Find the shapes of a ShapeNet-Part tree and their splits.

    Args:
        root: The dataset folder.

    Returns:
        The scan; listed shapes whose ``.pts`` file is missing are reported as skipped.

    Raises:
        DataError: Missing or malformed category or split files.
    """
    synsets = _categories(root)
    items: list[ShapeItem] = []
    skipped: list[tuple[str, str]] = []
    seen: set[str] = set()
    for split, file_name in _SPLIT_FILES.items():
        path = root / "train_test_split" / file_name
        try:
            entries = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError as err:
            raise DataError(f"{path}: missing split list") from err
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
            raise DataError(f"{path}: cannot read the split list: {err}") from err
        if not isinstance(entries, list) or not all(isinstance(e, str) for e in entries):
            raise DataError(f"{path}: expected a JSON list of 'shape_data/<synset>/<id>' strings")
        for entry in entries:
            parts = entry.strip("/").split("/")
            if len(parts) < 2:
                raise DataError(f"{path}: malformed entry {entry!r}")
            synset, shape_id = parts[-2], parts[-1]
            if synset not in synsets:
                continue  # a category left out of synsetoffset2category.txt
            key = f"{synset}/{shape_id}"
            if key in seen:
                continue
            seen.add(key)
            file = root / synset / "points" / f"{shape_id}.pts"
            if not file.is_file():
                skipped.append((str(file), f"listed in {file_name} but missing"))
                continue
            items.append(
                ShapeItem(
                    key=key,
                    name=safe_name(f"{synsets[synset]}_{shape_id}"),
                    category=synsets[synset],
                    path=str(file),
                    kind="cloud-file",
                    split=split,
                )
            )
    if not items:
        raise DataError(f"{root}: the split lists name no existing .pts file")
    return Scan(items=items, skipped=skipped, has_splits=True)
