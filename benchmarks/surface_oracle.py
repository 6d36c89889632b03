"""What a perfect completion scores: a fresh sample of the true surface, through the test protocol.

The test protocol scores a prediction of the missing region against the points of the shape's
fixed cloud that the crop removed (512 of 2,048 at 25 % missing). Those points are a random
sample of the surface, so even a network that knew the missing surface exactly could only
return another sample of it, and would not score 0 Chamfer or an F-score of 1. This script
scores that perfect predictor, to put the measured figures beside their ceiling::

    python benchmarks/surface_oracle.py --data data/sh3d-pool [--split test]
        [--missing-ratio 0.25] [--samples 3] [--threshold 0.01] [--json FILE]

``--data`` is a data set made with ``pfnet prepare --pool N`` (``N`` at least twice
``--points``) from meshes: its pool holds ``N - points`` more points of each shape's surface,
drawn after the cloud from the same area-weighted distribution and in the same normalised
coordinates; the first ``--points`` are the cloud that a data set prepared without ``--pool``
holds. For each shape of the split, each of ``--samples`` disjoint clouds of ``points`` pool
points is cropped at the shape's test viewpoint, and its missing region is scored against the
protocol's missing region with ``pfnet evaluate``'s metrics (mean over categories of the
per-shape means). The floor beside it: the partial input's own points nearest the viewpoint,
scored the same way. Only mesh sources qualify: the pool of a point-cloud file is its own points
again, not a fresh sample of the surface.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from pfnet.data import load_split, missing_count, test_protocol_crop
from pfnet.data.crops import test_protocol_viewpoints
from pfnet.data.format import read_manifest
from pfnet.errors import DataError, PfnetError
from pfnet.evaluation.metrics import sample_metrics, summarize
from pfnet.evaluation.scoring import SCALE
from pfnet.geometry import crop_by_viewpoint
from pfnet.io.files import atomic_path

MESH_SOURCES = ("sweethome3d", "procedural", "flightgear", "torcs", "crrcsim", "sweethome3d-app")
"""Source formats whose shapes are always meshes (``meshes`` folders may hold point files).
A data set of several sources qualifies when each of them is one of these."""


def oracle_scores(
    data: Path, split: str, missing_ratio: float, samples: int, threshold: float
) -> dict:
    """Score ``samples`` fresh surface samples of every shape of ``split`` as predictions.

    Returns:
        ``{"samples": int, "shapes": int, "oracle": scores, "floor": scores}``, each
        ``scores`` being ``{"categories": {cat: metrics}, "mean": metrics}`` with ``pfnet
        evaluate``'s metric names (Chamfer ×1000). ``oracle``: the fresh samples' missing
        regions; ``floor``: the partial input's own ``m`` points nearest the viewpoint (all of
        them when it has no more), what a
        completion that learned nothing could return.

    Raises:
        DataError: The data set has no pool of fresh surface samples, or the split no shapes.
        ConfigError: A bad missing ratio.
    """
    source = read_manifest(data).get("source", {})
    formats = [s.get("format") for s in source.get("sources", [source])]
    unfit = [f for f in formats if f not in MESH_SOURCES]
    if source.get("format") == "several" and unfit:
        raise DataError(
            f"{data}: prepared from several sources, among them {', '.join(map(repr, unfit))}; "
            f"only mesh sources ({', '.join(MESH_SOURCES)}) have pools that are fresh samples "
            "of the surface"
        )
    if unfit:
        raise DataError(
            f"{data}: prepared from {unfit[0]!r}; only mesh sources ({', '.join(MESH_SOURCES)}) "
            "have pools that are fresh samples of the surface"
        )
    clouds = load_split(data, split)
    n_points = clouds.points.shape[1]
    available = 0 if clouds.extra is None else clouds.extra.shape[1] // n_points
    if available < 1:
        raise DataError(
            f"{data}: needs a pool of at least {2 * n_points} points a shape "
            f"(pfnet prepare --pool {2 * n_points}); it has {clouds.pool_size}"
        )
    if len(clouds) == 0:
        raise DataError(f"{data}: split {split!r} has no shapes")
    samples = min(samples, available)
    partial, removed = test_protocol_crop(clouds.points, missing_ratio)
    viewpoints = test_protocol_viewpoints(len(clouds))
    m = missing_count(n_points, missing_ratio)
    categories = [str(c) for c in clouds.category]
    # crop_by_viewpoint takes a batch: one call for each fresh sample, shape-major after stacking
    fresh = np.stack(
        [
            crop_by_viewpoint(
                clouds.extra[:, k * n_points : (k + 1) * n_points], viewpoints, n_missing=m
            )[1]
            for k in range(samples)
        ],
        axis=1,
    ).reshape(-1, m, 3)
    # the partial keeps n - m points: all of them when that is not more than m
    keep = partial.shape[1]
    nearest = partial if m >= keep else crop_by_viewpoint(partial, viewpoints, n_missing=m)[1]
    oracle = _summary(fresh, np.repeat(removed, samples, axis=0), categories, samples, threshold)
    floor = _summary(nearest, removed, categories, 1, threshold)
    return {"samples": samples, "shapes": len(clouds), "oracle": oracle, "floor": floor}


def _summary(
    predictions: np.ndarray,
    truths: np.ndarray,
    categories: list[str],
    repeats: int,
    threshold: float,
) -> dict:
    """``pfnet evaluate``'s per-category and mean figures of ``repeats`` predictions a shape."""
    per_sample = sample_metrics(predictions, truths, threshold)
    summary = summarize(per_sample, np.repeat(categories, repeats), scale=float(SCALE))

    def row(metrics: dict) -> dict:
        chamfer = {k: float(metrics[k]) for k in ("pred_to_gt", "gt_to_pred")}
        return chamfer | {"cd_l2": sum(chamfer.values()), "f_score": float(metrics["f_score"])}

    return {
        "categories": {cat: row(r) for cat, r in summary["categories"].items()},
        "mean": row(summary["mean"]),
    }


def main(argv: list[str] | None = None) -> int:
    """Print (and optionally write) the perfect predictor's scores; return the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="data set with a pool")
    parser.add_argument("--split", default="test", choices=("train", "val", "test"))
    parser.add_argument("--missing-ratio", type=float, default=0.25)
    parser.add_argument("--samples", type=int, default=3, help="fresh clouds a shape")
    parser.add_argument("--threshold", type=float, default=0.01, help="F-score distance")
    parser.add_argument("--json", type=Path, help="write the scores here")
    args = parser.parse_args(argv)
    if args.samples < 1:
        parser.error(f"--samples must be at least 1, got {args.samples}")
    try:
        scores = oracle_scores(
            args.data, args.split, args.missing_ratio, args.samples, args.threshold
        )
    except PfnetError as err:
        sys.exit(f"error: {err}")
    print(
        f"a fresh surface sample as the prediction: {args.data} [{args.split}], "
        f"{scores['shapes']} shapes × {scores['samples']} samples, "
        f"{args.missing_ratio:.0%} missing; CD ×{SCALE:g}, F-score at {args.threshold:g}"
    )
    oracle, floor = scores["oracle"], scores["floor"]
    print(f"{'category':<12} {'Pred→GT':>9} {'GT→Pred':>9} {'CD-L2':>9} {'F':>7}")
    rows = [*oracle["categories"].items(), ("mean", oracle["mean"])]
    rows.append(("floor, mean", floor["mean"]))
    for name, r in rows:
        print(
            f"{name:<12} {r['pred_to_gt']:9.3f} {r['gt_to_pred']:9.3f} "
            f"{r['cd_l2']:9.3f} {r['f_score']:7.3f}"
        )
    print("floor: the partial input's own points nearest the viewpoint as the prediction")
    if args.json:
        with atomic_path(args.json) as part:
            part.write_text(json.dumps(scores, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
