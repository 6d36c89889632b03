"""Scoring the field's benchmarks (the work behind ``pfnet evaluate --protocol``): whole
completions against PCN's and ShapeNet-55/34's complete clouds with PoinTr's metrics, and
KITTI's cars by Fidelity and MMD against reference cars.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pfnet.errors import ConfigError, DataError
from pfnet.evaluation.protocols import check_protocol_data, get_protocol
from pfnet.evaluation.scoring import (
    FAR,
    MAX_WORKERS,
    SCALE,
    Evaluation,
    Notes,
    read_predictions,
    refuse_oversized,
    stack_if_equal,
)


def evaluate_benchmark(
    pred_dir: str | os.PathLike[str],
    data_dir: str | os.PathLike[str],
    protocol: str,
    *,
    split: str = "test",
    missing_ratio: float | None = None,
    workers: int | None = None,
    notes: Notes = None,
) -> Evaluation:
    """Score whole completions with a benchmark protocol (``pcn``, ``shapenet55``).

    Prediction files are ``PRED/<category>/<name>.<ext>`` (``pcn``) or
    ``PRED/<category>/<name>_view<v>.<ext>``, ``v`` = 0..7 (``shapenet55``: one completion
    per viewpoint of :data:`pfnet.evaluation.protocols.SHAPENET_VIEWPOINTS`), each the whole
    completion in the data set's coordinates, any point count. Each is compared with the
    shape's complete cloud by :func:`pfnet.evaluation.metrics.sample_metrics` with PoinTr's
    ``ignore_zeros``;
    per category the mean over its files, overall the unweighted mean of the categories (as
    PoinTr's ``test()``); CD-L1, CD-L2 and the two directed terms ×1000, the F-score at 0.01.

    Args:
        pred_dir: The prediction folder.
        data_dir: A data set, normally prepared from the benchmark's layout.
        protocol: A name of :data:`pfnet.evaluation.protocols.PROTOCOLS` other than ``pfnet``.
        split: The split scored.
        missing_ratio: ``shapenet55`` only: the ratio the inputs were cropped with (recorded
            in the report; the ground truth is the complete cloud whatever the ratio).
        workers: Threads reading files.
        notes: Called with a line for each category folder that cannot be listed (it is
            skipped; ``pfnet evaluate`` prints the line); none by default.

    Raises:
        ConfigError: Unknown protocol, or a ratio the protocol does not take.
        DataError: Missing folders, or no prediction could be scored.
    """
    from pfnet.data import load_split
    from pfnet.evaluation.metrics import sample_metrics, summarize
    from pfnet.evaluation.protocols import get_protocol

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
    present, loaded, missing, unmatched = read_predictions(pred_dir, keys, workers, notes)
    preds, gts, scored, unreadable, reasons = [], [], [], [], []
    for k, cloud in zip(present, loaded, strict=True):
        cloud = refuse_oversized(cloud, keys[k])
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
        stack_if_equal(preds), stack_if_equal(gts), 0.01, ignore_zeros=chosen.ignore_zeros
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
    notes: Notes = None,
) -> Evaluation:
    """Score completions of the KITTI cars by Fidelity and MMD (PoinTr ``KITTI_metric.py``).

    Prediction files are ``PRED/<category>/<name>.<ext>``, each a whole completion in PoinTr's
    normalised object frame (:func:`pfnet.data.kitti.object_pose`; what ``pfnet predict
    --protocol kitti`` writes). The input of each car is recomputed from the data set
    (:func:`pfnet.data.kitti.kitti_input`). As PoinTr's ``ignore_zeros=True`` at batch size
    1, points whose coordinates sum to exactly 0 are left out of inputs and completions.

    * Fidelity (lines 29–38): ``mean_I d(i, C)²``, input → completion
      (:func:`pfnet.evaluation.metrics.fidelity`). A method whose completion contains its input
      scores 0.
    * MMD (lines 82–99): ``min_R CD-L2(C, R)`` over the reference cars
      (:func:`pfnet.evaluation.metrics.minimal_matching_distance`, exact); the reference cars are
      taken as they are.

    Both ×1000 per category, overall the unweighted mean of the categories (one: ``car``).
    All completions, whatever their sizes, go to the Rust core in one call, which builds the
    reference cars' trees once. A category folder that cannot be listed is skipped and named to
    ``notes``.

    Raises:
        DataError: Missing folders, a data set without KITTI's boxes, unusable references,
            or no prediction could be scored.
    """
    from pfnet.data import load_split
    from pfnet.data.benchmarks import load_partials
    from pfnet.data.kitti import kitti_input, load_boxes
    from pfnet.evaluation.metrics import fidelity, minimal_matching_distance, zero_sum_mask

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
    present, loaded, missing, unmatched = read_predictions(pred_dir, keys, workers, notes)
    inputs, completions, scored, unreadable, reasons = [], [], [], [], []
    for k, cloud in zip(present, loaded, strict=True):
        cloud = refuse_oversized(cloud, keys[k])
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
