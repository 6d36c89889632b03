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

Scores come from :func:`pfnet.metrics.sample_metrics` and :func:`pfnet.metrics.summarize`:
per-category means, and the unweighted mean of the category means, Pred→GT and GT→Pred
reported ×1000 as in the paper's tables.
"""

from __future__ import annotations

import json
import os
import re
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pfnet.errors import ConfigError, DataError
from pfnet.inference import MAX_RECORD_BYTES
from pfnet.protocols import check_protocol_data, get_protocol

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


def find_prediction_files(pred_dir: Path, *, quiet: bool = False) -> dict[str, Path]:
    """Map ``<category>/<name>`` to its prediction file (first suffix in PREDICTION_SUFFIXES).

    A category entry that cannot be listed (a symlink loop, no permission) is named on
    stderr (unless ``quiet``) and skipped; its samples then count as missing.
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
                if not quiet:
                    print(f"skipped {cat.path}: {err.strerror or err}", file=sys.stderr)
                continue
            for entry in entries:
                stem, suffix = os.path.splitext(entry.name)
                suffix = suffix.lower()
                if suffix not in rank or entry.name.startswith("."):
                    continue
                key = f"{cat.name}/{stem}"
                if key not in found or rank[suffix] < found[key][0]:
                    found[key] = (rank[suffix], Path(entry.path))
    return {key: path for key, (_, path) in found.items()}


def _load(path: Path) -> np.ndarray | str:
    from pfnet.io import read_point_cloud

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

    Returns:
        An :class:`Evaluation`; samples without a usable file are listed, not scored.

    Raises:
        ConfigError: For a bad region, ratio or flag combination.
        DataError: If the folders are missing, or no prediction at all could be scored.
    """
    from pfnet.data import load_split, test_protocol_crop
    from pfnet.metrics import sample_metrics, summarize

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

    present, loaded, missing, unmatched = _read_predictions(pred_dir, sample_keys, workers)
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
    per_sample = sample_metrics(_stack_if_equal(preds), _stack_if_equal(gts), f_threshold)
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


def _read_predictions(
    pred_dir: Path, sample_keys: list[str], workers: int | None
) -> tuple[list[int], list, list[str], list[str]]:
    """Find and read the prediction file of each key (in a thread pool).

    Returns:
        The indices of the keys with a file, what was read for each (an array, or the
        reason it could not be used), the keys without a file, and files matching no key.
    """
    files = find_prediction_files(pred_dir)
    wanted = set(sample_keys)
    unmatched = sorted(str(p) for k, p in files.items() if k not in wanted)
    present = [i for i, key in enumerate(sample_keys) if key in files]
    missing = [key for key in sample_keys if key not in files]
    n_workers = workers or min(8, (os.cpu_count() or 1) + 4)
    with ThreadPoolExecutor(max_workers=n_workers) as pool:
        loaded = list(pool.map(_load, [files[sample_keys[i]] for i in present], chunksize=64))
    return present, loaded, missing, unmatched


def evaluate_benchmark(
    pred_dir: str | os.PathLike[str],
    data_dir: str | os.PathLike[str],
    protocol: str,
    *,
    split: str = "test",
    missing_ratio: float | None = None,
    workers: int | None = None,
) -> Evaluation:
    """Score whole completions with a benchmark protocol (``pcn``, ``shapenet55``).

    Prediction files are ``PRED/<category>/<name>.<ext>`` (``pcn``) or
    ``PRED/<category>/<name>_view<v>.<ext>``, ``v`` = 0..7 (``shapenet55``: one completion
    per viewpoint of :data:`pfnet.protocols.SHAPENET_VIEWPOINTS`), each the whole completion
    in the data set's coordinates, any point count. Each is compared with the shape's
    complete cloud by :func:`pfnet.metrics.sample_metrics` with PoinTr's ``ignore_zeros``;
    per category the mean over its files, overall the unweighted mean of the categories (as
    PoinTr's ``test()``); CD-L1, CD-L2 and the two directed terms ×1000, the F-score at 0.01.

    Args:
        pred_dir: The prediction folder.
        data_dir: A data set, normally prepared from the benchmark's layout.
        protocol: A name of :data:`pfnet.protocols.PROTOCOLS` other than ``pfnet``.
        split: The split scored.
        missing_ratio: ``shapenet55`` only: the ratio the inputs were cropped with (recorded
            in the report; the ground truth is the complete cloud whatever the ratio).
        workers: Threads reading files.

    Raises:
        ConfigError: Unknown protocol, or a ratio the protocol does not take.
        DataError: Missing folders, or no prediction could be scored.
    """
    from pfnet.data import load_split
    from pfnet.metrics import sample_metrics, summarize
    from pfnet.protocols import get_protocol

    chosen = get_protocol(protocol)
    if chosen.prediction != "complete":
        raise ConfigError(f"protocol {chosen.name!r} is scored by evaluate_predictions")
    if chosen.name == "kitti":
        raise ConfigError("the kitti protocol is scored by evaluate_kitti (against reference cars)")
    if chosen.ratios and missing_ratio is None:
        missing_ratio = chosen.default_ratio
    if not chosen.ratios and missing_ratio is not None:
        raise ConfigError(
            f"the {chosen.name} protocol takes no missing ratio (its inputs are given)"
        )
    if missing_ratio is not None and not 0.0 < missing_ratio < 1.0:
        raise ConfigError(f"missing ratio must be in (0, 1), got {missing_ratio}")
    if workers is not None and not 1 <= workers <= MAX_WORKERS:
        raise ConfigError(f"workers must be in [1, {MAX_WORKERS}], got {workers}")
    pred_dir = Path(pred_dir)
    if not pred_dir.is_dir():
        raise DataError(f"prediction folder {pred_dir} does not exist")
    check_protocol_data(chosen, data_dir)
    clouds = load_split(data_dir, split)
    points = np.asarray(clouds.points)
    keys, owner = [], []
    for i, (cat, name) in enumerate(zip(clouds.category, clouds.name, strict=True)):
        for key in chosen.sample_keys(str(cat), str(name)):
            keys.append(key)
            owner.append(i)
    present, loaded, missing, unmatched = _read_predictions(pred_dir, keys, workers)
    preds, gts, scored, unreadable, reasons = [], [], [], [], []
    for k, cloud in zip(present, loaded, strict=True):
        cloud = _refuse_oversized(cloud, keys[k])
        if isinstance(cloud, np.ndarray) and chosen.ignore_zeros:
            if not (cloud.astype(np.float32).sum(axis=1, dtype=np.float32) != 0).any():
                cloud = f"{keys[k]}: every point has x + y + z = 0 (PoinTr leaves such points out)"
        if isinstance(cloud, str):
            unreadable.append(keys[k])
            reasons.append(cloud)
            continue
        preds.append(cloud)
        gts.append(points[owner[k]])
        scored.append(k)
    if not scored:
        raise DataError(
            f"no prediction in {pred_dir} could be scored against {split!r} of "
            f"{data_dir} ({len(missing)} missing, {len(unreadable)} unreadable of "
            f"{len(keys)} files; expected files like {pred_dir / keys[0]}.npy)"
            if keys
            else f"split {split!r} of {data_dir} has no samples"
        )
    categories = [str(clouds.category[owner[k]]) for k in scored]
    per_sample = sample_metrics(
        _stack_if_equal(preds), _stack_if_equal(gts), 0.01, ignore_zeros=chosen.ignore_zeros
    )
    summary = summarize(per_sample, categories, scale=float(SCALE), scaled=chosen.scaled)
    names = ("pred_to_gt", "gt_to_pred", "cd_l2", "cd_l1", "f_score")
    report = {
        "protocol": chosen.name,
        "split": split,
        "scale": SCALE,
        "scaled": list(chosen.scaled),
        "headline": chosen.headline,
        "missing_ratio": None if missing_ratio is None else float(missing_ratio),
        "categories": {
            cat: {"n": int(row["n"]), **{k: float(row[k]) for k in names}}
            for cat, row in summary["categories"].items()
        },
        "mean": {k: float(summary["mean"][k]) for k in names},
        "missing": missing,
        "unreadable": unreadable,
    }
    return Evaluation(
        report=report,
        categories=categories,
        names=[keys[k].split("/", 1)[1] for k in scored],
        per_sample={k: np.asarray(v, dtype=np.float64) for k, v in per_sample.items()},
        missing=missing,
        unreadable=unreadable,
        reasons=reasons,
        unmatched=unmatched,
        n_samples=len(keys),
        far=[keys[k] for k, p in zip(scored, preds, strict=True) if np.abs(p).max() > FAR],
    )


def recorded_protocol(
    pred_dir: str | os.PathLike[str],
) -> tuple[str, float | None, int | None] | None:
    """The split, missing ratio and points per cloud ``PRED/predictions.json`` records (the
    points ``None`` in records of older pfnet versions, the ratio ``None`` for a protocol
    with given inputs), or None without a record.

    Predictions made by ``pfnet predict`` record their split and crop; scoring them with
    another crop compares each prediction with the wrong missing region, silently.

    Raises:
        DataError: If the record exists but cannot be read.
    """
    info = _read_record(pred_dir)
    if info is None:
        return None
    protocol = info["protocol"]
    ratio = protocol.get("missing_ratio")
    return info["split"], None if ratio is None else float(ratio), protocol.get("n_points")


def recorded_data_problem(
    pred_dir: str | os.PathLike[str], data_dir: str | os.PathLike[str], split: str
) -> str | None:
    """Why ``PRED/predictions.json`` says its predictions come from other clouds than the
    ``split`` of ``data_dir`` (the digest of the split file differs), or None (the same
    clouds, or a record without a digest or of another split, which other checks report).

    Raises:
        DataError: If the record exists but cannot be read.
    """
    from pfnet.data.format import split_digest

    info = _read_record(pred_dir)
    if info is None or info["split"] != split or "split_sha256" not in info:
        return None
    if split_digest(data_dir, split) == info["split_sha256"]:
        return None
    made_from = info.get("data") if isinstance(info.get("data"), str) else "another data set"
    return (
        f"{pred_dir} was predicted from other {split} clouds than those of {data_dir} (the "
        f"digest its predictions.json records differs; made from {made_from[:200]!r}): score "
        "it against the data set it was predicted on, or pass --ignore-recorded-protocol"
    )


def _read_record(pred_dir: str | os.PathLike[str]) -> dict[str, Any] | None:
    """``PRED/predictions.json``, checked by :func:`_record_problem`, or None without one."""
    record = Path(pred_dir) / "predictions.json"
    if not record.exists() and not record.is_symlink():
        return None
    if not record.is_file():  # a folder here was once taken for no record at all
        raise DataError(f"cannot read {record}: not a file")
    if record.stat().st_size > MAX_RECORD_BYTES:  # predict lists its files within the bound
        raise DataError(
            f"cannot read {record}: larger than {MAX_RECORD_BYTES >> 20} MB, not pfnet "
            "predict's record"
        )
    try:
        info = json.loads(record.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError) as err:
        # ValueError: bad UTF-8 or JSON; RecursionError: forged nesting
        raise DataError(f"cannot read {record} ({type(err).__name__}: {str(err)[:120]})") from None
    problem = _record_problem(info)
    if problem is not None:
        raise DataError(f"{record}: {problem}")
    if info.get("complete") is False:
        raise DataError(
            f"{record} says its prediction run stopped before writing every file (the "
            "folder may mix old and new predictions); run pfnet predict again"
        )
    return info


def _record_problem(info: Any) -> str | None:
    """What is wrong with a ``predictions.json`` document, or None.

    Types are exact, as :func:`pfnet.inference.predict_split` writes them: a string
    ``"false"`` is not a boolean, ``"0.25"`` not a ratio, ``true`` not a count (``bool`` is an
    ``int`` to Python). Keys that older pfnet versions did not write (``complete``,
    ``n_points``, ``model``) may be absent.
    """
    from pfnet.models.config import is_int, is_number

    def shown(value: Any) -> str:
        return json.dumps(value)[:40] if not isinstance(value, float) else repr(value)

    if not isinstance(info, dict):
        return f"expected a JSON object, got {type(info).__name__}"
    if not isinstance(info.get("complete", False), bool):
        return f'"complete" must be true or false, got {shown(info["complete"])}'
    if not isinstance(info.get("split"), str):
        return f'"split" must be a split\'s name, got {shown(info.get("split"))}'
    digest = info.get("split_sha256", "0" * 64)  # older records have none
    if not (isinstance(digest, str) and re.fullmatch(r"[0-9a-f]{64}", digest)):
        return f'"split_sha256" must be a SHA-256 in hex, got {shown(digest)}'
    protocol = info.get("protocol")
    if not isinstance(protocol, dict):
        return f'"protocol" must be an object, got {shown(protocol)}'
    name = protocol.get("name", "test")  # "test": PF-Net's protocol, as older records name it
    if not isinstance(name, str):
        return f'"protocol.name" must be a protocol\'s name, got {shown(name)}'
    from pfnet.formats import MAX_CLOUD_POINTS
    from pfnet.protocols import PROTOCOL_NAMES, PROTOCOLS

    if name != "test" and name.lower() not in PROTOCOL_NAMES:
        return (
            f'"protocol.name" must be one of test, {", ".join(PROTOCOL_NAMES)}, got {shown(name)}'
        )
    benchmark = name not in ("test", "pfnet")
    ratio = protocol.get("missing_ratio")
    # A benchmark protocol with given inputs (pcn) records no ratio.
    if not (ratio is None and benchmark or is_number(ratio) and 0 < ratio < 1):
        return f'"protocol.missing_ratio" must be a number in (0, 1), got {shown(ratio)}'
    model = info.get("model", {})
    if not isinstance(model, dict):
        return f'"model" must be an object, got {shown(model)}'
    counts = {
        "protocol.n_points": protocol.get("n_points"),
        "model.n_points": model.get("n_points"),
        "model.n_input": model.get("n_input"),
        "model.n_predicted": model.get("n_predicted"),
    }
    # informational, but bounded as every count pfnet reads: no cloud holds more points
    for key, count in counts.items():
        if count is not None and not (is_int(count) and 1 <= count <= MAX_CLOUD_POINTS):
            return (
                f'"{key}" must be a positive integer of at most {MAX_CLOUD_POINTS}, '
                f"got {shown(count)}"
            )
    views, most = protocol.get("views"), max(p.views for p in PROTOCOLS.values())
    if views is not None and not (is_int(views) and 1 <= views <= most):
        return f'"protocol.views" must be a positive integer of at most {most}, got {shown(views)}'
    points, trained = counts["protocol.n_points"], counts["model.n_points"]
    # Benchmark protocols resample their clouds to the model's input, as complete does.
    if not benchmark and None not in (points, trained) and points != trained:
        return (
            f"its model was trained on clouds of {trained} points but predicted clouds of "
            f"{points}: the scores would compare regions of different sizes"
        )
    return None


def recorded_protocol_name(pred_dir: str | os.PathLike[str]) -> str | None:
    """The protocol name ``PRED/predictions.json`` records (``pfnet`` for records of older
    pfnet versions, which name it ``test``), or None without a record.

    Raises:
        DataError: If the record exists but cannot be read.
    """
    if recorded_protocol(pred_dir) is None:
        return None
    info = json.loads((Path(pred_dir) / "predictions.json").read_text(encoding="utf-8"))
    name = info["protocol"].get("name", "test")
    return "pfnet" if name == "test" else str(name)


def _refuse_oversized(cloud: np.ndarray | str, key: str) -> np.ndarray | str:
    """A completion of more than :data:`MAX_SCORED_POINTS` points as the reason it is not
    scored (what :func:`_load` gives for a file it cannot read); anything else as it is."""
    if isinstance(cloud, np.ndarray) and len(cloud) > MAX_SCORED_POINTS:
        return (
            f"{key}: a completion of {len(cloud)} points; at most {MAX_SCORED_POINTS:,} are "
            "scored (PoinTr's have 16,384): thin it first"
        )
    return cloud


def _stack_if_equal(clouds: list[np.ndarray]) -> np.ndarray | list[np.ndarray]:
    """One ``(B, P, 3)`` array when every cloud has the same size (the fast batched path)."""
    if len({len(c) for c in clouds}) == 1:
        return np.stack(clouds)
    return clouds


def render_evaluation_gallery(
    out: Path,
    evaluation: Evaluation,
    pred_dir: Path,
    data_dir: Path,
    *,
    split: str,
    missing_ratio: float,
    count: int,
    columns: dict[str, Path] | None = None,
) -> Path:
    """Render ``count`` scored samples (spread over the categories) as partial/pred/gt rows.

    ``columns`` (title -> prediction folder) draws several models' completions of the same
    samples side by side instead of ``pred_dir``'s alone.
    """
    from pfnet.gallery import pick_gallery, render_completions

    chosen = pick_gallery(evaluation.categories, count)
    return render_completions(
        out,
        data_dir,
        columns or {"completion": pred_dir},
        split=split,
        missing_ratio=missing_ratio,
        keys=[(evaluation.categories[k], evaluation.names[k]) for k in chosen],
        title=f"{pred_dir.name}: {split}, {missing_ratio:.0%} missing",
    )


KITTI_METRICS = ("fidelity", "mmd")
"""The ``kitti`` protocol's per-sample metrics, in table order."""


def load_references(
    root: str | os.PathLike[str], category: str = "car"
) -> tuple[np.ndarray, list[str]]:
    """The reference cars of KITTI's MMD: every cloud of ``category`` in every split of a
    prepared data set (PoinTr uses PCN's cars, train + test + val: ``KITTI_metric.py`` lines
    13–19), in the data set's coordinates.

    Returns:
        float32 ``(R, M, 3)`` clouds and their ``<split>/<name>`` labels.

    Raises:
        DataError: The folder is not a data set, has no cloud of ``category``, or its clouds
            hold no points (a KITTI data set).
    """
    from pfnet.data import SPLITS, load_split

    found, labels = [], []
    available: set[str] = set()
    for split in SPLITS:
        try:
            clouds = load_split(root, split)
        except DataError as err:
            raise DataError(f"references: {err}") from None
        available.update(clouds.categories)
        chosen = clouds.category == category
        if chosen.any():
            found.append(np.asarray(clouds.points[chosen], dtype=np.float32))
            labels += [f"{split}/{n}" for n in clouds.name[chosen]]
    if not found:
        raise DataError(
            f"references {root}: no cloud of the category {category!r} (categories: "
            f"{', '.join(sorted(available)) or 'none'})"
        )
    refs = np.concatenate(found)
    if refs.shape[1] == 0:
        raise DataError(
            f"references {root}: its clouds hold no points (a KITTI data set has no complete "
            "cars); use complete car clouds, e.g. PCN's cars"
        )
    return refs, labels


def evaluate_kitti(
    pred_dir: str | os.PathLike[str],
    data_dir: str | os.PathLike[str],
    references: str | os.PathLike[str],
    *,
    reference_category: str = "car",
    split: str = "test",
    workers: int | None = None,
) -> Evaluation:
    """Score completions of the KITTI cars by Fidelity and MMD (PoinTr ``KITTI_metric.py``).

    Prediction files are ``PRED/<category>/<name>.<ext>``, each a whole completion in PoinTr's
    normalised object frame (:func:`pfnet.data.kitti.object_pose`; what ``pfnet predict
    --protocol kitti`` writes). The input of each car is recomputed from the data set
    (:func:`pfnet.data.kitti.kitti_input`). As PoinTr's ``ignore_zeros=True`` at batch size
    1, points whose coordinates sum to exactly 0 are left out of inputs and completions.

    * Fidelity (lines 29–38): ``mean_I d(i, C)²``, input → completion
      (:func:`pfnet.metrics.fidelity`). A method whose completion contains its input
      scores 0.
    * MMD (lines 82–99): ``min_R CD-L2(C, R)`` over the reference cars
      (:func:`pfnet.metrics.minimal_matching_distance`, exact); the reference cars are
      taken as they are.

    Both ×1000 per category, overall the unweighted mean of the categories (one: ``car``).
    All completions, whatever their sizes, go to the Rust core in one call, which builds the
    reference cars' trees once.

    Raises:
        DataError: Missing folders, a data set without KITTI's boxes, unusable references,
            or no prediction could be scored.
    """
    from pfnet.data import load_split
    from pfnet.data.benchmarks import load_partials
    from pfnet.data.kitti import kitti_input, load_boxes
    from pfnet.metrics import fidelity, minimal_matching_distance, zero_sum_mask

    if workers is not None and not 1 <= workers <= MAX_WORKERS:
        raise ConfigError(f"workers must be in [1, {MAX_WORKERS}], got {workers}")
    pred_dir = Path(pred_dir)
    if not pred_dir.is_dir():
        raise DataError(f"prediction folder {pred_dir} does not exist")
    check_protocol_data(get_protocol("kitti"), data_dir)
    cars = load_split(data_dir, split)
    if len(cars) == 0:
        raise DataError(f"split {split!r} of {data_dir} has no samples")
    boxes = load_boxes(data_dir, split, len(cars))
    partials = load_partials(data_dir, split, len(cars))
    refs, ref_labels = load_references(references, reference_category)
    keys = [f"{c}/{n}" for c, n in zip(cars.category, cars.name, strict=True)]
    present, loaded, missing, unmatched = _read_predictions(pred_dir, keys, workers)
    inputs, completions, scored, unreadable, reasons = [], [], [], [], []
    for k, cloud in zip(present, loaded, strict=True):
        cloud = _refuse_oversized(cloud, keys[k])
        if isinstance(cloud, np.ndarray):
            cloud = cloud[zero_sum_mask(cloud)]
            if not len(cloud):
                cloud = f"{keys[k]}: every point has x + y + z = 0 (PoinTr leaves such points out)"
        given = kitti_input(partials[k], boxes[k], keys[k])
        given = given[zero_sum_mask(given)]
        if not len(given):
            cloud = f"{keys[k]}: every input point has x + y + z = 0; no Fidelity"
        if isinstance(cloud, str):
            unreadable.append(keys[k])
            reasons.append(cloud)
            continue
        inputs.append(given)
        completions.append(np.ascontiguousarray(cloud, dtype=np.float32))
        scored.append(k)
    if not scored:
        raise DataError(
            f"no prediction in {pred_dir} could be scored against {split!r} of "
            f"{data_dir} ({len(missing)} missing, {len(unreadable)} unreadable of "
            f"{len(keys)} cars; expected files like {pred_dir / keys[0]}.npy)"
        )
    fid = fidelity(inputs, completions)
    # one call for completions of every size: each reference's tree is built once
    mmd, nearest = minimal_matching_distance(completions, refs)
    categories = [str(cars.category[k]) for k in scored]
    per_sample = {"fidelity": np.asarray(fid, np.float64), "mmd": mmd}
    table: dict[str, dict] = {}
    for cat in sorted(set(categories)):
        sel = np.array([c == cat for c in categories])
        row: dict = {"n": int(sel.sum())}
        row.update({m: float(per_sample[m][sel].mean()) * SCALE for m in KITTI_METRICS})
        table[cat] = row
    report = {
        "protocol": "kitti",
        "split": split,
        "scale": SCALE,
        "scaled": list(KITTI_METRICS),
        "headline": "mmd",
        "missing_ratio": None,
        "categories": table,
        "mean": {m: float(np.mean([row[m] for row in table.values()])) for m in KITTI_METRICS},
        "references": {
            "path": str(Path(references).resolve()),
            "category": reference_category,
            "n": len(refs),
            "points": int(refs.shape[1]),
        },
        "missing": missing,
        "unreadable": unreadable,
    }
    return Evaluation(
        report=report,
        categories=categories,
        names=[keys[k].split("/", 1)[1] for k in scored],
        per_sample=per_sample,
        missing=missing,
        unreadable=unreadable,
        reasons=reasons,
        unmatched=unmatched,
        n_samples=len(keys),
        far=[keys[k] for k, c in zip(scored, completions, strict=True) if np.abs(c).max() > FAR],
        labels={"nearest_reference": [ref_labels[i] for i in nearest]},
    )
