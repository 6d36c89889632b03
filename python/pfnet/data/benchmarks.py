"""The completion benchmarks of later work, read in their published layouts.

``pfnet prepare`` turns them into pfnet data sets that keep the benchmark's splits, point
counts and coordinates, so ``pfnet evaluate --protocol`` scores in the benchmark's units.
Users bring the data; nothing here downloads it. Layouts as PoinTr's ``DATASET.md`` and
loaders (``datasets/PCNDataset.py``, ``datasets/ShapeNet55Dataset.py``) describe them.

**PCN** (``--format pcn``)::

    ROOT/PCN.json                                  [{"taxonomy_id", "taxonomy_name",
                                                     "train": [model, ...], "val", "test"}]
    ROOT/category.txt                              category names, one a line (not needed)
    ROOT/{train,val,test}/complete/<taxonomy>/<model>.pcd          16,384 points
    ROOT/{train,val,test}/partial/<taxonomy>/<model>/{00..07}.pcd  partial scans (00 only
                                                                   in val and test)

Categories are PCN.json's ``taxonomy_name`` (``airplane``, ``cabinet``...); without
PCN.json the folders are listed and the taxonomy id is the category. Clouds keep PCN's
coordinates (PoinTr does not normalise them). The partial scan ``00.pcd`` of every shape
is stored as given (any number of points) in ``<split>.partial.npz``; training crops the
complete clouds as usual and does not use the other seven scans.

**ShapeNet-55 / ShapeNet-34** (``--format shapenet-55``, ``shapenet-34``,
``shapenet-unseen21``)::

    ROOT/shapenet_pc/<taxonomy>-<model>.npy        8,192 points
    ROOT/ShapeNet-55/{train,test}.txt              "<taxonomy>-<model>.npy" a line
    ROOT/ShapeNet-34/{train,test}.txt
    ROOT/ShapeNet-Unseen21/test.txt

Each cloud is normalised as PoinTr's ``pc_norm`` does (centroid at the origin, divided by
the largest distance to it). The category is the taxonomy (synset) id. There is no val split.

**KITTI** (``--format kitti``): the cars of the PCN release (``cars/``, ``bboxes/``,
``KITTI.json``), test split only, without ground truth; see :mod:`pfnet.data.kitti`.
"""

from __future__ import annotations

import json
import os
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pfnet.data.archives import load_side_file
from pfnet.data.format import (
    SPLITS,
    CloudSet,
    skipped_entries,
    write_dataset,
)
from pfnet.data.layouts import (
    PARTIAL_SUFFIX,
    bad_entry,
    file_id,
    keep_categories,
    read_index,
    repeated,
    shown,
)
from pfnet.errors import DataError

__all__ = [
    "BENCHMARK_FORMATS",
    "PCN_POINTS",
    "SHAPENET_POINTS",
    "detect_benchmark",
    "load_partials",
    "prepare_benchmark",
]

PCN_POINTS = 16384
SHAPENET_POINTS = 8192
SHAPENET_LISTS = {
    "shapenet-55": "ShapeNet-55",
    "shapenet-34": "ShapeNet-34",
    "shapenet-unseen21": "ShapeNet-Unseen21",
}
BENCHMARK_FORMATS: tuple[str, ...] = ("pcn", *SHAPENET_LISTS, "kitti")
"""The benchmark layouts ``pfnet prepare --format`` reads."""

PROTOCOL_OF = {"pcn": "pcn", **dict.fromkeys(SHAPENET_LISTS, "shapenet55")}
# A partial scan of PCN has a few hundred to a few thousand points.
MAX_PARTIAL_POINTS = 1 << 20


@dataclass(frozen=True)
class _Entry:
    split: str
    category: str
    model: str
    complete: Path
    partial: Path | None


def detect_benchmark(root: Path) -> str | None:
    """The benchmark layout of ``root`` (``pcn``, ``shapenet-55``... or ``kitti``), or None."""
    from pfnet.data.kitti import detect_kitti

    if not root.is_dir():
        return None
    if detect_kitti(root):
        return "kitti"
    if (root / "PCN.json").is_file() or any(
        (root / split / "complete").is_dir() for split in SPLITS
    ):
        return "pcn"
    if (root / "shapenet_pc").is_dir():
        for fmt, folder in SHAPENET_LISTS.items():
            if (root / folder).is_dir():
                return fmt
    return None


def _pcn_entries(root: Path) -> tuple[list[_Entry], list[tuple[str, str]]]:
    index = root / "PCN.json"
    listed: list[tuple[str, str, str, str]] = []  # split, taxonomy, name, model
    if index.is_file():
        try:
            records = json.loads(read_index(index, "category file"))
            for record in records:
                taxonomy, name = str(record["taxonomy_id"]), str(record["taxonomy_name"])
                for split in SPLITS:
                    listed += [(split, taxonomy, name, str(m)) for m in record.get(split, [])]
        except (OSError, ValueError, KeyError, TypeError, RecursionError) as err:
            raise DataError(
                f"{index}: cannot read the category file ({type(err).__name__}: {err}); "
                'expected [{"taxonomy_id", "taxonomy_name", "train": [...], ...}]'
            ) from None
    else:
        for split in SPLITS:
            folder = root / split / "complete"
            if not folder.is_dir():
                continue
            for taxonomy in sorted(p for p in folder.iterdir() if p.is_dir()):
                listed += [
                    (split, taxonomy.name, taxonomy.name, f.stem)
                    for f in sorted(taxonomy.glob("*.pcd"))
                ]
    entries, skipped = [], []
    first: dict[tuple, tuple[str, str]] = {}
    repeats: Counter = Counter()
    for split, taxonomy, name, model in listed:
        bad = bad_entry(index, taxonomy, name, model)
        if bad is not None:
            skipped.append(bad)
            continue
        complete = root / split / "complete" / taxonomy / f"{model}.pcd"
        partial = root / split / "partial" / taxonomy / model / "00.pcd"
        ident = file_id(complete)
        if ident is None:
            skipped.append((str(complete), "listed in PCN.json but missing"))
        elif (split, ident) in first:  # one model listed twice, or under many categories
            repeats[(split, ident)] += 1
        elif file_id(partial) is None:
            skipped.append((str(partial), "the partial scan 00.pcd is missing"))
        else:
            first[(split, ident)] = (str(complete), f"{split}/{name}/{model}")
            entries.append(_Entry(split, name, model, complete, partial))
    return entries, skipped + repeated(repeats, first, "PCN.json")


def _shapenet_entries(root: Path, fmt: str) -> tuple[list[_Entry], list[tuple[str, str]]]:
    lists = root / SHAPENET_LISTS[fmt]
    clouds = root / "shapenet_pc"
    if not clouds.is_dir():
        raise DataError(f"{root}: no shapenet_pc folder (the {fmt} layout keeps clouds there)")
    entries, skipped = [], []
    found = False
    for split in ("train", "test"):
        path = lists / f"{split}.txt"
        if not path.is_file():
            continue
        found = True
        lines = read_index(path, "split list").split()
        first: dict[tuple, tuple[str, str]] = {}
        repeats: Counter = Counter()
        for line in lines:
            stem = line.removesuffix(".npy")
            taxonomy, _, model = stem.partition("-")
            bad = bad_entry(path, line)
            if bad is not None:
                skipped.append(bad)
                continue
            if not taxonomy or not model:
                skipped.append((f"{path}: {shown(line)}", "not '<taxonomy>-<model>.npy'"))
                continue
            file = clouds / f"{stem}.npy"
            ident = file_id(file)
            if ident is None:
                skipped.append(
                    (str(file), f"listed in {SHAPENET_LISTS[fmt]}/{split}.txt but missing")
                )
            elif ident in first:  # a repeated line, or a hard link
                repeats[ident] += 1
            else:
                first[ident] = (str(file), f"{split}/{taxonomy}/{model}")
                entries.append(_Entry(split, taxonomy, model, file, None))
        skipped += repeated(repeats, first, f"{SHAPENET_LISTS[fmt]}/{split}.txt")
    if not found:
        raise DataError(f"{lists}: no train.txt or test.txt split list")
    return entries, skipped


def _read(entry: _Entry, fmt: str) -> tuple[np.ndarray | None, np.ndarray | None, str]:
    from pfnet.data.sampling import normalize, unit_ball
    from pfnet.io.clouds import read_point_cloud

    expected = PCN_POINTS if fmt == "pcn" else SHAPENET_POINTS
    try:
        complete = read_point_cloud(entry.complete)
        if len(complete) != expected:
            return None, None, f"has {len(complete)} points; {fmt} clouds have {expected}"
        partial = None
        if entry.partial is not None:
            partial = read_point_cloud(entry.partial)
            if len(partial) > MAX_PARTIAL_POINTS:
                return None, None, f"{entry.partial}: more than {MAX_PARTIAL_POINTS} points"
            # no shape to score, or no scan to complete (predict's input is normalised)
            if unit_ball(complete) is None:
                return None, None, f"all {len(complete)} points of the complete cloud coincide"
            if unit_ball(partial) is None:
                return (
                    None,
                    None,
                    (
                        f"{entry.partial}: all {len(partial)} points of the partial scan coincide; "
                        "nothing to complete"
                    ),
                )
        if fmt != "pcn":  # PoinTr's pc_norm
            complete = normalize(complete)
        return np.asarray(complete, np.float32), partial, ""
    except DataError as err:
        return None, None, str(err).removeprefix(f"{entry.complete}: ")


def prepare_benchmark(
    source: str | os.PathLike[str],
    out: str | os.PathLike[str],
    fmt: str,
    *,
    categories: list[str] | None = None,
    workers: int | None = None,
    strict: bool = False,
    overwrite: bool = False,
):
    """Write a pfnet data set from a PCN or ShapeNet-55/34 tree (layouts in the module doc),
    or from the KITTI layout (:func:`pfnet.data.kitti.prepare_kitti`).

    Returns:
        A :class:`pfnet.data.prepared.PrepareReport`.

    Raises:
        DataError: A malformed index, no readable shape, or (``strict``) any bad file.
    """
    from pfnet import __version__
    from pfnet.data.prepared import PrepareReport
    from pfnet.data.sources import unique_names

    if fmt == "kitti":
        from pfnet.data.kitti import prepare_kitti

        return prepare_kitti(
            source, out, categories=categories, workers=workers, strict=strict, overwrite=overwrite
        )
    start = time.perf_counter()
    root = Path(source)
    if not root.is_dir():
        raise DataError(f"{root}: the {fmt} format needs a folder")
    entries, skipped = _pcn_entries(root) if fmt == "pcn" else _shapenet_entries(root, fmt)
    entries = keep_categories(entries, categories)
    if strict and skipped:
        raise DataError(f"{skipped[0][0]}: {skipped[0][1]}")
    if not entries:
        raise DataError(f"{root}: no shapes to prepare in the {fmt} layout")
    names = unique_names({f"{e.split}/{e.category}/{e.model}": e.model for e in entries})
    with ThreadPoolExecutor(max_workers=workers or min(8, (os.cpu_count() or 1) + 2)) as pool:
        results = list(pool.map(lambda e: _read(e, fmt), entries))
    kept: dict[str, list] = {split: [] for split in SPLITS}
    for entry, (complete, partial, reason) in zip(entries, results, strict=True):
        if complete is None:
            if strict:
                raise DataError(f"{entry.complete}: {reason}")
            skipped.append((str(entry.complete), reason))
            continue
        name = names[f"{entry.split}/{entry.category}/{entry.model}"]
        kept[entry.split].append((entry.category, name, complete, partial))
    if not any(kept.values()):
        raise DataError(f"{root}: every shape failed ({skipped[0][0]}: {skipped[0][1]})")
    n_points = PCN_POINTS if fmt == "pcn" else SHAPENET_POINTS
    cloud_sets, partials = {}, {}
    for split in SPLITS:
        rows = sorted(kept[split], key=lambda r: (r[0], r[1]))
        if not rows:
            cloud_sets[split] = CloudSet.empty(n_points)
        else:
            cloud_sets[split] = CloudSet(
                np.stack([r[2] for r in rows]),
                np.array([r[0] for r in rows], dtype=str),
                np.array([r[1] for r in rows], dtype=str),
            )
        if fmt == "pcn":
            clouds = [r[3] for r in rows]
            offsets = np.zeros(len(clouds) + 1, np.int64)
            offsets[1:] = np.cumsum([len(c) for c in clouds])
            points = np.concatenate(clouds) if clouds else np.zeros((0, 3), np.float32)
            partials[f"{split}{PARTIAL_SUFFIX}"] = {"points": points, "offsets": offsets}
    counts = {
        split: dict(sorted(Counter(cloud_sets[split].category.tolist()).items()))
        for split in SPLITS
    }
    manifest = {
        "format": "pfnet-completion-dataset",
        "version": 1,
        "pfnet_version": __version__,
        "source": {"format": fmt, "path": str(source)},
        "points": n_points,
        "seed": 0,
        "split": "from the source",
        "normalization": (
            "none: PCN's coordinates"
            if fmt == "pcn"
            else "PoinTr's pc_norm: centroid at the origin, divided by the max radius"
        ),
        "up_axis": "as in the source",
        "benchmark": {
            "name": fmt,
            "protocol": PROTOCOL_OF[fmt],
            "partials": "view 00.pcd of each shape, as given" if fmt == "pcn" else None,
        },
        "categories": sorted({c for split in counts.values() for c in split}),
        "splits": {
            split: {"total": sum(counts[split].values()), "categories": counts[split]}
            for split in SPLITS
        },
        "licenses": [
            {
                "source": "ShapeNet" if fmt != "pcn" else "PCN (ShapeNet)",
                "license": "ShapeNet's terms of use: non-commercial research and education",
            }
        ],
        "dropped": {},
        **skipped_entries(skipped),
    }
    out_path = write_dataset(out, cloud_sets, manifest, overwrite=overwrite, side_files=partials)
    return PrepareReport(
        out=out_path,
        format=fmt,
        counts=counts,
        skipped=skipped,
        seconds=time.perf_counter() - start,
        manifest=manifest,
    )


def load_partials(root: str | os.PathLike[str], split: str, n_shapes: int) -> list[np.ndarray]:
    """The given partial scans of a split (PCN), in the split's shape order.

    Raises:
        DataError: The data set has no partial scans, or the file is malformed.
    """
    path = Path(root) / f"{split}{PARTIAL_SUFFIX}"
    if not path.is_file():
        raise DataError(
            f"{path}: no partial scans; the pcn protocol needs a data set prepared from the "
            "PCN layout"
        )
    arrays = load_side_file(
        path,
        {"points": (np.float32, (None, 3)), "offsets": (np.int64, (n_shapes + 1,))},
        "partial scans",
    )
    points, offsets = arrays["points"], arrays["offsets"]
    if offsets[0] != 0 or np.any(np.diff(offsets) < 1):
        raise DataError(f"{path}: offsets must start at 0 and increase")
    if offsets[-1] > n_shapes * MAX_PARTIAL_POINTS:
        raise DataError(f"{path}: claims {offsets[-1]} partial points")
    if len(points) != int(offsets[-1]):
        raise DataError(f"{path}: points must be float32 ({offsets[-1]}, 3), got {points.shape}")
    return [points[offsets[i] : offsets[i + 1]] for i in range(n_shapes)]
