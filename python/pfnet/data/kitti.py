"""KITTI cars as the PCN release ships them, and PoinTr's pose normalisation of each car.

Layout (PoinTr ``cfgs/dataset_configs/KITTI.yaml``, ``datasets/KITTIDataset.py``)::

    ROOT/KITTI.json                  [{"taxonomy_id": "kitti-car", "taxonomy_name": "Car",
                                       "train": [], "val": [], "test": [<id>, ...]}]
    ROOT/cars/<id>.pcd               the car's LiDAR points (sensor frame), e.g.
                                     cars/frame_0_car_0.pcd
    ROOT/bboxes/<id>.txt             its box: 8 corners, one "x y z" line each

There is a test split only (2,401 cars) and no ground truth. Without ``KITTI.json`` every
``cars/*.pcd`` is a test car. ``pfnet prepare`` stores each car as given (points and box);
the pose normalisation below is applied by ``pfnet predict --protocol kitti`` and by
``pfnet evaluate --protocol kitti``, so the stored data stay the release's.

**Pose normalisation** (PoinTr ``datasets/data_transforms.py`` lines 110–134,
``NormalizeObjectPose``, after PCN's ``test_kitti.py``): with the box ``B`` (8, 3) read as
float32, ``c = (min B + max B) / 2``; ``yaw = atan2(B₃y − B₀y, B₃x − B₀x)`` (corners 0 and 3
span the car's length); ``R`` the rotation by ``yaw`` about z; ``s`` the length of ``B₃ − B₀``
after ``(B − c)·R``; then ``p' = ((p − c)·R / s)·S`` where ``S`` swaps y and z (KITTI is
z-up, ShapeNet's cars y-up). A car ends up centred on its box, facing +x, one unit long.
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

from pfnet.errors import DataError

__all__ = [
    "BOXES_SUFFIX",
    "KITTI_INPUT_POINTS",
    "ObjectPose",
    "detect_kitti",
    "kitti_input",
    "load_boxes",
    "object_pose",
    "prepare_kitti",
]

BOXES_SUFFIX = ".boxes.npz"
KITTI_INPUT_POINTS = 2048
"""Points of PoinTr's KITTI input (``RandomSamplePoints`` with ``n_points: 2048``)."""
# A KITTI car has a few to a few thousand LiDAR points.
MAX_CAR_POINTS = 1 << 20
# A car's points lie in its box (a return or two just outside); a car with none within this
# many box lengths of the box's centre is a cloud and a box that do not belong together.
MAX_CAR_DISTANCE = 3.0
_SWAP_YZ = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])


@dataclass(frozen=True)
class ObjectPose:
    """PoinTr's ``NormalizeObjectPose`` as a transform (see the module docstring).

    Attributes:
        centre: float64 ``(3,)``, the box's centre in the sensor frame.
        rotation: float64 ``(3, 3)``, the rotation by the box's yaw about z.
        scale: The box's length; divided after the rotation.
    """

    centre: np.ndarray
    rotation: np.ndarray
    scale: float

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Sensor-frame ``(N, 3)`` points -> float32 normalised ones (y up, length 1)."""
        moved = (np.asarray(points, np.float64) - self.centre) @ self.rotation / self.scale
        return (moved @ _SWAP_YZ).astype(np.float32)

    def invert(self, points: np.ndarray) -> np.ndarray:
        """Normalised ``(N, 3)`` points -> float32 points in the sensor frame."""
        moved = (np.asarray(points, np.float64) @ _SWAP_YZ) * self.scale
        return (moved @ self.rotation.T + self.centre).astype(np.float32)


def object_pose(box: np.ndarray, source: str = "box") -> ObjectPose:
    """The pose normalisation of a car from its box (8 corners, PoinTr's corner order).

    Raises:
        DataError: The box is not 8 finite corners, or corners 0 and 3 coincide in x and y
            (no yaw, no length).
    """
    corners = np.asarray(box)
    if corners.shape != (8, 3) or not np.isfinite(corners).all():
        raise DataError(f"{source}: a box must be 8 finite corners (8, 3), got {corners.shape}")
    # PoinTr reads the box as float32 (KITTIDataset.py line 70), then computes in float64.
    corners = corners.astype(np.float32).astype(np.float64)
    centre = (corners.min(axis=0) + corners.max(axis=0)) / 2
    corners = corners - centre
    yaw = np.arctan2(corners[3, 1] - corners[0, 1], corners[3, 0] - corners[0, 0])
    cos, sin = np.cos(yaw), np.sin(yaw)
    rotation = np.array([[cos, -sin, 0.0], [sin, cos, 0.0], [0.0, 0.0, 1.0]])
    turned = corners @ rotation
    scale = float(turned[3, 0] - turned[0, 0])
    if not (np.isfinite(scale) and scale > 1e-9):
        raise DataError(
            f"{source}: corners 0 and 3 of the box coincide in x and y; they must span the "
            "car's length"
        )
    return ObjectPose(centre=centre, rotation=rotation, scale=scale)


def kitti_input(points: np.ndarray, box: np.ndarray, source: str = "car") -> np.ndarray:
    """The KITTI protocol's input of one car: its points pose-normalised (:func:`object_pose`),
    and, above :data:`KITTI_INPUT_POINTS`, reduced to that many by farthest point sampling
    from the first point.

    PoinTr draws a random subset of 2,048 instead (``RandomSamplePoints``, unseeded) and pads
    fewer points with zeros, which its metrics then leave out (``ignore_zeros``); this input is
    deterministic and has no padding.

    Returns:
        float32 ``(min(N, 2048), 3)``.

    Raises:
        DataError: Points that are not finite ``(N, 3)``, or a box :func:`object_pose` refuses.
    """
    from pfnet.geometry import farthest_point_sample

    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise DataError(f"{source}: points must have shape (N, 3), got {points.shape}")
    if not np.isfinite(points).all():
        raise DataError(f"{source}: points must be finite; some coordinates are NaN or infinite")
    cloud = object_pose(box, f"{source} (box)").apply(points)
    if len(cloud) > KITTI_INPUT_POINTS:
        cloud = cloud[farthest_point_sample(cloud, KITTI_INPUT_POINTS, start_index=0)]
    return np.ascontiguousarray(cloud, dtype=np.float32)


# ---------------------------------------------------------------- the layout


def detect_kitti(root: Path) -> bool:
    """Whether ``root`` holds the KITTI layout (``KITTI.json``, or ``cars/`` and ``bboxes/``)."""
    return root.is_dir() and (
        (root / "KITTI.json").is_file() or ((root / "cars").is_dir() and (root / "bboxes").is_dir())
    )


@dataclass(frozen=True)
class _Car:
    category: str
    model: str
    cloud: Path
    box: Path


def _kitti_entries(root: Path) -> tuple[list[_Car], list[tuple[str, str]]]:
    from pfnet.data.layouts import bad_entry, file_id, read_index, repeated

    index = root / "KITTI.json"
    listed: list[tuple[str, str]] = []  # category, model
    if index.is_file():
        try:
            records = json.loads(read_index(index, "category file"))
            for record in records:
                name = str(record.get("taxonomy_name", record["taxonomy_id"])).lower()
                listed += [(name, str(m)) for m in record.get("test", [])]
        except (OSError, ValueError, KeyError, TypeError, AttributeError, RecursionError) as err:
            raise DataError(
                f"{index}: cannot read the category file ({type(err).__name__}: {err}); "
                'expected [{"taxonomy_id", "taxonomy_name", "test": [...]}]'
            ) from None
    elif (root / "cars").is_dir():
        listed = [("car", f.stem) for f in sorted((root / "cars").glob("*.pcd"))]
    entries, skipped = [], []
    first: dict[tuple, tuple[str, str]] = {}
    repeats: Counter = Counter()
    for category, model in listed:
        bad = bad_entry(index, category, model)
        if bad is not None:
            skipped.append(bad)
            continue
        cloud, box = root / "cars" / f"{model}.pcd", root / "bboxes" / f"{model}.txt"
        ident = file_id(cloud)
        if ident is None:
            skipped.append((str(cloud), "listed in KITTI.json but missing"))
        elif ident in first:  # one car listed twice, or under many categories
            repeats[ident] += 1
        elif file_id(box) is None:
            skipped.append((str(box), f"the box of {cloud.name} is missing"))
        else:
            first[ident] = (str(cloud), f"{category}/{model}")
            entries.append(_Car(category, model, cloud, box))
    return entries, skipped + repeated(repeats, first, "KITTI.json")


def _read_car(car: _Car) -> tuple[np.ndarray | None, np.ndarray | None, str, str]:
    """``(points, box, "", "")`` or ``(None, None, path, reason)``."""
    from pfnet.io.clouds import read_point_cloud

    try:
        points = read_point_cloud(car.cloud)
    except DataError as err:
        return None, None, str(car.cloud), str(err).removeprefix(f"{car.cloud}: ")
    if len(points) > MAX_CAR_POINTS:
        return None, None, str(car.cloud), f"more than {MAX_CAR_POINTS} points"
    try:
        box = read_point_cloud(car.box)
        if box.shape != (8, 3):
            raise DataError(f"{car.box}: a box has 8 corners, this file holds {len(box)} points")
        pose = object_pose(box, str(car.box))
    except DataError as err:
        return None, None, str(car.box), str(err).removeprefix(f"{car.box}: ")
    # in box lengths, in float64: points at 1e15 and a box 4e-6 long leave float32
    moved = (np.asarray(points, np.float64) - pose.centre) @ pose.rotation / pose.scale
    nearest = float(np.abs(moved).max(axis=1).min())
    if nearest > MAX_CAR_DISTANCE:
        reason = (
            f"no point within {MAX_CAR_DISTANCE:g} box lengths of the centre of its box "
            f"{car.box.name} (the nearest is {nearest:.3g} lengths away): the cloud and the "
            "box do not belong together"
        )
        return None, None, str(car.cloud), reason
    return points, box, "", ""


def prepare_kitti(
    source: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    categories: list[str] | None = None,
    workers: int | None = None,
    strict: bool = False,
    overwrite: bool = False,
):
    """Write a pfnet data set from the KITTI layout (module docstring).

    The data set has a test split only. Its ``test.npz`` names the cars (``points`` holds
    none: there is no ground truth); ``test.partial.npz`` holds each car's points as given
    (``points`` (T, 3), ``offsets`` (S+1,)) and ``test.boxes.npz`` its box (``boxes``
    float32 (S, 8, 3)). Cars whose cloud or box is missing or unreadable are skipped and
    named in the report and the manifest.

    Returns:
        A :class:`pfnet.data.prepared.PrepareReport`.

    Raises:
        DataError: A malformed ``KITTI.json``, no readable car, or (``strict``) any bad file.
    """
    from pfnet import __version__
    from pfnet.data.format import SPLITS, CloudSet, skipped_entries, write_dataset
    from pfnet.data.layouts import PARTIAL_SUFFIX, keep_categories
    from pfnet.data.prepared import PrepareReport
    from pfnet.data.sources import unique_names

    start = time.perf_counter()
    root = Path(source)
    if not root.is_dir():
        raise DataError(f"{root}: the kitti format needs a folder")
    entries, skipped = _kitti_entries(root)
    entries = keep_categories(entries, categories)
    if strict and skipped:
        raise DataError(f"{skipped[0][0]}: {skipped[0][1]}")
    if not entries:
        raise DataError(f"{root}: no cars to prepare in the kitti layout (cars/*.pcd)")
    names = unique_names({f"{e.category}/{e.model}": e.model for e in entries})
    with ThreadPoolExecutor(max_workers=workers or min(8, (os.cpu_count() or 1) + 2)) as pool:
        results = list(pool.map(_read_car, entries))
    rows = []
    for entry, (points, box, path, reason) in zip(entries, results, strict=True):
        if points is None:
            if strict:
                raise DataError(f"{path}: {reason}")
            skipped.append((path, reason))
            continue
        rows.append((entry.category, names[f"{entry.category}/{entry.model}"], points, box))
    if not rows:
        raise DataError(f"{root}: every car failed ({skipped[0][0]}: {skipped[0][1]})")
    rows.sort(key=lambda r: (r[0], r[1]))
    test = CloudSet(
        np.zeros((len(rows), 0, 3), np.float32),
        np.array([r[0] for r in rows], dtype=str),
        np.array([r[1] for r in rows], dtype=str),
    )
    offsets = np.zeros(len(rows) + 1, np.int64)
    offsets[1:] = np.cumsum([len(r[2]) for r in rows])
    side_files = {
        f"test{PARTIAL_SUFFIX}": {
            "points": np.concatenate([r[2] for r in rows]).astype(np.float32),
            "offsets": offsets,
        },
        f"test{BOXES_SUFFIX}": {"boxes": np.stack([r[3] for r in rows]).astype(np.float32)},
    }
    splits = {split: CloudSet.empty(0) for split in SPLITS}
    splits["test"] = test
    counts = {
        split: dict(sorted(Counter(splits[split].category.tolist()).items())) for split in SPLITS
    }
    manifest = {
        "format": "pfnet-completion-dataset",
        "version": 1,
        "pfnet_version": __version__,
        "source": {"format": "kitti", "path": str(source)},
        "seed": 0,
        "split": "from the source (test only)",
        "normalization": "none: the sensor frame; PoinTr's NormalizeObjectPose is applied by "
        "predict and evaluate",
        "up_axis": "z (KITTI's sensor frame)",
        "benchmark": {
            "name": "kitti",
            "protocol": "kitti",
            "partials": "each car's LiDAR points as given",
            "boxes": f"test{BOXES_SUFFIX}: 8 corners a car, as given",
            "ground_truth": None,
        },
        "categories": sorted({c for split in counts.values() for c in split}),
        "splits": {
            split: {"total": sum(counts[split].values()), "categories": counts[split]}
            for split in SPLITS
        },
        "licenses": [
            {
                "source": "KITTI (via PCN)",
                "license": "KITTI's terms: Creative Commons Attribution-NonCommercial-ShareAlike "
                "3.0",
            }
        ],
        "dropped": {},
        **skipped_entries(skipped),
    }
    out_path = write_dataset(out, splits, manifest, overwrite=overwrite, side_files=side_files)
    return PrepareReport(
        out=out_path,
        format="kitti",
        counts=counts,
        skipped=skipped,
        seconds=time.perf_counter() - start,
        manifest=manifest,
    )


def load_boxes(root: str | os.PathLike[str], split: str, n_cars: int) -> np.ndarray:
    """The cars' boxes of a split, float32 ``(S, 8, 3)``, in the split's order.

    Raises:
        DataError: The data set has no boxes (it was not prepared from the KITTI layout), or
            the file is malformed.
    """
    path = Path(root) / f"{split}{BOXES_SUFFIX}"
    if not path.is_file():
        raise DataError(
            f"{path}: no boxes; the kitti protocol needs a data set prepared from the KITTI "
            "layout (cars/, bboxes/, KITTI.json)"
        )
    from pfnet.data.archives import load_side_file

    return load_side_file(path, {"boxes": (np.float32, (n_cars, 8, 3))}, "boxes")["boxes"]
