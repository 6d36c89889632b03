"""Scoring a folder of predictions against a data set split (the work behind ``pfnet evaluate``).

A prediction folder holds one file per sample, ``PRED/<category>/<name>.<ext>`` with ``ext``
one of ``.npy .ply .pcd .xyz .pts .txt`` (the first found in that order). The ground truth comes
from the deterministic test protocol (DESIGN.md §3, :func:`pfnet.data.test_protocol_crop`):
sample *i* of the split loses the ``round(r·N)`` points nearest ``VIEWPOINTS[i % 5]``.

Regions (DESIGN.md §5):

* ``missing``: the file holds the predicted missing region (any point count), scored
  against the removed points.
* ``whole``: the file holds the predicted missing region, merged with the partial input
  before scoring, or (``pred_is_complete``) a full completion; scored against the complete
  cloud.

Scores come from :func:`pfnet.evaluation.metrics.sample_metrics` and
:func:`pfnet.evaluation.metrics.summarize`:
per-category means, and the unweighted mean of the category means, Pred→GT and GT→Pred
reported ×1000 as in the paper's tables. The field's benchmarks (``--protocol``) are scored
by :mod:`pfnet.evaluation.benchmarks`; the record ``predictions.json`` is read by
:mod:`pfnet.evaluation.prediction_record`.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pfnet.errors import ConfigError, DataError

Notes = Callable[[str], None] | None
"""What a caller hears of a folder skipped while scoring (the command prints it)."""

PREDICTION_SUFFIXES: tuple[str, ...] = (".npy", ".ply", ".pcd", ".xyz", ".pts", ".txt")
"""Suffixes a prediction file may have, in the order they are looked for."""

REGIONS = ("missing", "whole")
# Data sets are normalised into the unit ball; a prediction reaching beyond this radius is
# in other coordinates (a scan's own units, another normalisation) and is flagged.
FAR = 10.0
SCALE = 1000
# Threads reading prediction files: more only contend for the disk.
MAX_WORKERS = 256
# Points of one scored completion (kitti, pcn, shapenet55). PoinTr's completions have 16,384
# and pfnet's at most 2,560; scoring costs completion points × reference clouds (KITTI's
# MMD: a 3,000,000-point file took a minute against 12 cars, hours against PCN's 5,927).
MAX_SCORED_POINTS = 1 << 17
_JSON_METRICS = ("pred_to_gt", "gt_to_pred", "cd_l1", "f_score")


@dataclass
class Evaluation:
    """The outcome of :func:`evaluate_predictions`.

    Attributes:
        report: The JSON summary ``pfnet evaluate --json`` writes (schema in the README).
        categories: Category of each scored sample, ``(K,)``.
        names: Name of each scored sample, ``(K,)``.
        per_sample: Raw per-sample metrics (float64 ``(K,)`` arrays, not scaled).
        missing: ``<category>/<name>`` of samples without a prediction file.
        unreadable: ``<category>/<name>`` of samples whose file could not be used.
        reasons: Why each unreadable file was rejected (one line each).
        unmatched: Prediction files that match no sample of the split.
        n_samples: Number of samples in the split.
        far: ``<category>/<name>`` of scored predictions with points more than
            :data:`FAR` from the origin, where the data set's clouds lie within radius 1:
            predictions in other coordinates, scored but probably not what was meant.
        labels: More per-sample text columns, ``{column: (K,) strings}`` (the ``kitti``
            protocol's nearest reference car).
    """

    report: dict
    categories: list[str]
    names: list[str]
    per_sample: dict[str, np.ndarray]
    missing: list[str] = field(default_factory=list)
    unreadable: list[str] = field(default_factory=list)
    reasons: list[str] = field(default_factory=list)
    unmatched: list[str] = field(default_factory=list)
    n_samples: int = 0
    far: list[str] = field(default_factory=list)
    labels: dict[str, list[str]] = field(default_factory=dict)


def find_prediction_files(pred_dir: Path, *, notes: Notes = None) -> dict[str, Path]:
    """Map ``<category>/<name>`` to its prediction file (a suffix of PREDICTION_SUFFIXES).

    A category entry that cannot be listed (a symlink loop, no permission) is skipped, and
    named to ``notes`` if given; its samples then count as missing.

    Raises:
        DataError: Two files for one sample (``x.npy`` and ``x.ply``), naming both: which
            one holds the prediction is not pfnet's to guess (one was ignored silently).
    """
    rank = {s: i for i, s in enumerate(PREDICTION_SUFFIXES)}
    found: dict[str, tuple[int, Path]] = {}
    with os.scandir(pred_dir) as categories:
        for cat in categories:
            try:
                if not cat.is_dir() or cat.name.startswith("."):
                    continue
                with os.scandir(cat.path) as listing:
                    entries = list(listing)
            except OSError as err:
                if notes is not None:
                    notes(f"skipped {cat.path}: {err.strerror or err}")
                continue
            for entry in entries:
                stem, suffix = os.path.splitext(entry.name)
                suffix = suffix.lower()
                if suffix not in rank or entry.name.startswith("."):
                    continue
                key = f"{cat.name}/{stem}"
                if key in found:
                    first, second = sorted([found[key][1], Path(entry.path)])
                    raise DataError(
                        f"{first} and {second} are two predictions of the sample {key}; "
                        "keep one of them"
                    )
                found[key] = (rank[suffix], Path(entry.path))
    return {key: path for key, (_, path) in found.items()}


def _load(path: Path) -> np.ndarray | str:
    from pfnet.io.clouds import read_point_cloud

    try:
        return read_point_cloud(path)
    except DataError as err:
        return str(err)


def evaluate_predictions(
    pred_dir: str | os.PathLike[str],
    data_dir: str | os.PathLike[str],
    *,
    split: str = "test",
    missing_ratio: float = 0.25,
    region: str = "missing",
    pred_is_complete: bool = False,
    f_threshold: float = 0.01,
    workers: int | None = None,
    notes: Notes = None,
) -> Evaluation:
    """Score the prediction files in ``pred_dir`` against split ``split`` of ``data_dir``.

    Args:
        pred_dir: Folder of ``<category>/<name>.<ext>`` prediction files.
        data_dir: A prepared data set (DESIGN.md §3).
        split: ``train``, ``val`` or ``test``.
        missing_ratio: Fraction of points the test protocol removes, in ``(0, 1)``.
        region: ``"missing"`` or ``"whole"``.
        pred_is_complete: With ``region="whole"``, files hold full completions and are
            scored as they are instead of being merged with the partial input.
        f_threshold: Distance threshold of the F-score.
        workers: Threads reading files (default: ``min(8, cpu count + 4)``).
        notes: Called with a line for each category folder that cannot be listed (it is
            skipped; ``pfnet evaluate`` prints the line); none by default.

    Returns:
        An :class:`Evaluation`; samples without a usable file are listed, not scored.

    Raises:
        ConfigError: For a bad region, ratio or flag combination.
        DataError: If the folders are missing, or no prediction at all could be scored.
    """
    from pfnet.data import load_split, test_protocol_crop
    from pfnet.evaluation.metrics import sample_metrics, summarize

    if region not in REGIONS:
        raise ConfigError(f"region must be one of {REGIONS}, got {region!r}")
    if pred_is_complete and region != "whole":
        raise ConfigError("complete predictions (pred_is_complete) need the region 'whole'")
    if not 0.0 < missing_ratio < 1.0:
        raise ConfigError(f"missing ratio must be in (0, 1), got {missing_ratio}")
    if workers is not None and not 1 <= workers <= MAX_WORKERS:
        raise ConfigError(f"workers must be in [1, {MAX_WORKERS}], got {workers}")
    pred_dir = Path(pred_dir)
    if not pred_dir.is_dir():
        raise DataError(f"prediction folder {pred_dir} does not exist")
    clouds = load_split(data_dir, split)
    points = np.asarray(clouds.points)
    sample_keys = [f"{c}/{n}" for c, n in zip(clouds.category, clouds.name, strict=True)]
    partial, removed = test_protocol_crop(points, missing_ratio)

    present, loaded, missing, unmatched = read_predictions(pred_dir, sample_keys, workers, notes)
    preds, gts, scored, unreadable, reasons = [], [], [], [], []
    for i, cloud in zip(present, loaded, strict=True):
        if isinstance(cloud, str):
            unreadable.append(sample_keys[i])
            reasons.append(cloud)
            continue
        if region == "missing":
            preds.append(cloud)
            gts.append(removed[i])
        else:
            preds.append(cloud if pred_is_complete else np.concatenate([partial[i], cloud]))
            gts.append(points[i])
        scored.append(i)
    if not scored:
        raise DataError(
            f"no prediction in {pred_dir} could be scored against {split!r} of "
            f"{data_dir} ({len(missing)} missing, {len(unreadable)} unreadable of "
            f"{len(sample_keys)} samples; expected files like "
            f"{pred_dir / sample_keys[0]}.npy)"
            if sample_keys
            else f"split {split!r} of {data_dir} has no samples"
        )
    categories = [str(clouds.category[i]) for i in scored]
    per_sample = sample_metrics(stack_if_equal(preds), stack_if_equal(gts), f_threshold)
    summary = summarize(per_sample, categories, scale=float(SCALE))
    report = {
        "region": region,
        "scale": SCALE,
        "missing_ratio": float(missing_ratio),
        "categories": {
            cat: {"n": int(row["n"]), **{k: float(row[k]) for k in _JSON_METRICS}}
            for cat, row in summary["categories"].items()
        },
        "mean": {k: float(summary["mean"][k]) for k in _JSON_METRICS},
        "missing": missing,
        "unreadable": unreadable,
    }
    return Evaluation(
        report=report,
        categories=categories,
        names=[str(clouds.name[i]) for i in scored],
        per_sample={k: np.asarray(v, dtype=np.float64) for k, v in per_sample.items()},
        missing=missing,
        unreadable=unreadable,
        reasons=reasons,
        unmatched=unmatched,
        n_samples=len(sample_keys),
        far=[sample_keys[i] for i, p in zip(scored, preds, strict=True) if np.abs(p).max() > FAR],
    )


def read_predictions(
    pred_dir: Path, sample_keys: list[str], workers: int | None, notes: Notes = None
) -> tuple[list[int], list, list[str], list[str]]:
    """Find and read the prediction file of each key (in a thread pool); a category folder
    that cannot be listed is named to ``notes`` (:func:`find_prediction_files`).

    Returns:
        The indices of the keys with a file, what was read for each (an array, or the
        reason it could not be used), the keys without a file, and files matching no key.
    """
    files = find_prediction_files(pred_dir, notes=notes)
    wanted = set(sample_keys)
    unmatched = sorted(str(p) for k, p in files.items() if k not in wanted)
    present = [i for i, key in enumerate(sample_keys) if key in files]
    missing = [key for key in sample_keys if key not in files]
    n_workers = workers or min(8, (os.cpu_count() or 1) + 4)
    with ThreadPoolExecutor(max_workers=n_workers) as pool:
        loaded = list(pool.map(_load, [files[sample_keys[i]] for i in present], chunksize=64))
    return present, loaded, missing, unmatched


def refuse_oversized(cloud: np.ndarray | str, key: str) -> np.ndarray | str:
    """A completion of more than :data:`MAX_SCORED_POINTS` points as the reason it is not
    scored (what :func:`_load` gives for a file it cannot read); anything else as it is."""
    if isinstance(cloud, np.ndarray) and len(cloud) > MAX_SCORED_POINTS:
        return (
            f"{key}: a completion of {len(cloud)} points; at most {MAX_SCORED_POINTS:,} are "
            "scored (PoinTr's have 16,384): thin it first"
        )
    return cloud


def stack_if_equal(clouds: list[np.ndarray]) -> np.ndarray | list[np.ndarray]:
    """One ``(B, P, 3)`` array when every cloud has the same size (the fast batched path)."""
    if len({len(c) for c in clouds}) == 1:
        return np.stack(clouds)
    return clouds
