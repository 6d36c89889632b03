"""Fit check: can a generator memorise a handful of training shapes with pfnet's own loop?

A model that cannot fit 16 shapes cannot be compared with anything. This script takes the
first ``--shapes`` training shapes of a prepared data set (spread over its categories),
makes them both the train and the val split of a scratch data set, trains on them with
``pfnet train``'s loop for ``--steps`` optimiser steps, and reports the training Chamfer and
the validation CD-L2 ×1000 on the same shapes (test protocol, eval mode) over the run::

    python benchmarks/fit_check.py --data data/sh3d --out runs/fit [--model pfnet-vanilla]
        [--shapes 16] [--batch-size 16] [--lr 1e-3] [--steps 2000] [--milestones 0.5 0.75]
        [--target 1.0] [--config KEYS.toml] [--oracle-data data/sh3d-all]

The run is sized in steps (``--steps``) with the learning rate multiplied by the preset's
``lr_gamma`` at ``--milestones`` (fractions of the run; none for a constant rate).

**What a perfect completion scores on the same cuts** (``--oracle-data``): the validation cuts
are scored against the 512 points of each shape's fixed cloud that the crop removed, a random
sample of the surface, so a network that had learnt the shapes' surfaces exactly, and no more,
would score what another sample of the same surface scores (``benchmarks/surface_oracle.py``).
Given a data set prepared with ``--pool`` from the same meshes that holds the same shapes with
the same clouds (``pfnet prepare ... --categories all --pool 8192`` holds SweetHome3D's), the
report adds that figure (``surface_oracle``): a fit below it memorises the particular points
of each cloud, not only its surface.

It exits with 0 when the best validation CD-L2 of the last tenth of the run is at most
``--target``, else 1. Re-running with the same ``--out`` resumes the run.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from pathlib import Path

import numpy as np

from pfnet.data.format import (
    SPLITS,
    CloudSet,
    load_split,
    read_manifest,
    split_record,
    write_dataset,
)
from pfnet.errors import DataError
from pfnet.training import preset_config, train
from pfnet.training.config import load_config


def fit_subset(data: Path, out: Path, shapes: int) -> Path:
    """A data set whose train and val splits are the same ``shapes`` training shapes."""
    source = load_split(data, "train")
    by_category: dict[str, list[int]] = {}
    for i, category in enumerate(source.category.tolist()):
        by_category.setdefault(category, []).append(i)
    chosen: list[int] = []
    while len(chosen) < min(shapes, len(source)):  # round robin over the categories
        for indices in by_category.values():
            if indices and len(chosen) < shapes:
                chosen.append(indices.pop(0))
    chosen.sort()
    subset = CloudSet(source.points[chosen], source.category[chosen], source.name[chosen])
    empty = CloudSet(
        np.zeros((0, *source.points.shape[1:]), np.float32),
        np.zeros(0, source.category.dtype),
        np.zeros(0, source.name.dtype),
    )
    splits = {"train": subset, "val": subset, "test": empty}
    manifest = dict(read_manifest(data))
    manifest["note"] = f"fit check: {len(chosen)} training shapes of {data} as train and val"
    manifest["splits"] = {name: split_record(clouds) for name, clouds in splits.items()}
    return write_dataset(out, splits, manifest, overwrite=True)


def oracle_subset(fit_data: Path, pooled: Path, out: Path) -> Path:
    """The fit check's shapes with their pools of fresh surface points, taken from ``pooled``.

    ``pooled`` is a data set prepared with ``--pool`` from the same meshes: each of the fit
    check's shapes must be in one of its splits, by name, with the same cloud.

    Raises:
        DataError: A shape is not in ``pooled``, its cloud differs, or ``pooled`` has no pool.
    """
    fit = load_split(fit_data, "train")
    found: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for split in SPLITS:
        clouds = load_split(pooled, split)
        if clouds.extra is None:
            raise DataError(f"{pooled} has no pool of surface points (pfnet prepare --pool)")
        for i, name in enumerate(clouds.name.tolist()):
            found.setdefault(name, (clouds.points[i], clouds.extra[i]))
    extra = []
    for i, name in enumerate(fit.name.tolist()):
        if name not in found:
            raise DataError(f"{pooled} does not hold the fit check's shape {name!r}")
        points, pool = found[name]
        if not np.array_equal(points, fit.points[i]):
            raise DataError(
                f"{pooled} holds another cloud of {name!r}: prepare it from the same source "
                "with the same --points and --seed"
            )
        extra.append(pool)
    subset = CloudSet(fit.points, fit.category, fit.name, np.stack(extra))
    splits = {"train": subset, "val": subset, "test": subset}
    manifest = dict(read_manifest(pooled))
    manifest["note"] = f"the fit check's {len(fit)} shapes with their pools from {pooled}"
    manifest["splits"] = {name: split_record(clouds) for name, clouds in splits.items()}
    return write_dataset(out, splits, manifest, overwrite=True)


def surface_oracle(fit_data: Path, pooled: Path, out: Path, missing_ratio: float) -> dict:
    """``benchmarks/surface_oracle.py``'s figures on the fit check's validation cuts."""
    spec = importlib.util.spec_from_file_location(
        "surface_oracle", Path(__file__).with_name("surface_oracle.py")
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    scores = module.oracle_scores(
        oracle_subset(fit_data, pooled, out), "val", missing_ratio, samples=3, threshold=0.01
    )
    return {"samples": scores["samples"]} | scores["oracle"]["mean"]


def main(argv: list[str] | None = None) -> int:
    """Run the fit check; return the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="a prepared data set")
    parser.add_argument("--out", type=Path, required=True, help="scratch folder (resumable)")
    parser.add_argument("--model", default="pfnet-vanilla")
    parser.add_argument("--preset", default="small")
    parser.add_argument(
        "--config", type=Path, default=None, help="TOML file of config keys over the preset"
    )
    parser.add_argument("--shapes", type=int, default=16)
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--lr", type=float, default=None, help="default: the preset's")
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--milestones", type=float, nargs="*", default=[0.5, 0.75])
    parser.add_argument("--target", type=float, default=1.0, help="val CD-L2 ×1000 to reach")
    parser.add_argument(
        "--adversarial-weight", type=float, default=None, help="λ_adv (default: the preset's)"
    )
    parser.add_argument("--device", default="auto")
    parser.add_argument(
        "--oracle-data",
        type=Path,
        default=None,
        help="a data set with a pool holding the same shapes: report a perfect completion's score",
    )
    args = parser.parse_args(argv)

    data = args.out / "data"
    if not (data / "manifest.json").is_file():
        fit_subset(args.data, data, args.shapes)
    base = (
        load_config(args.config, preset=args.preset) if args.config else preset_config(args.preset)
    )
    config = base.replace(
        model=args.model,
        batch_size=args.batch_size,
        lr=args.lr,
        steps=args.steps,
        lr_milestones=tuple(args.milestones),
        # its val split is its training shapes: one cut each, as every fit check before
        val_views=1,
    )
    if args.adversarial_weight is not None:
        config = config.replace(adversarial_weight=args.adversarial_weight)
    # before the run, so that a data set that does not hold the shapes stops it at once
    oracle = (
        surface_oracle(data, args.oracle_data, args.out / "oracle", config.missing_ratio)
        if args.oracle_data
        else None
    )
    run = args.out / "run"
    resume = (run / "last.pt").is_file()
    train(config, data, run, device=args.device, resume=resume, progress=sys.stderr.isatty())
    rows = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()][1:]
    tail = rows[-max(1, len(rows) // 10) :]
    best = min(tail, key=lambda r: r["val_cd_l2"])
    report = {
        "model": args.model,
        "shapes": args.shapes,
        "batch_size": args.batch_size,
        "lr": config.lr,
        "steps": rows[-1]["step"],
        "milestones": list(config.lr_milestones),
        "adversarial_weight": config.adversarial_weight,
        # cd_detail is loss_scale · (Pred→GT + GT→Pred); ×1000 / loss_scale gives CD-L2 ×1000.
        "train_cd_l2_last_tenth": float(
            np.mean([r["cd_detail"] for r in tail]) * 1000 / config.loss_scale
        ),
        "val_cd_l2_best_last_tenth": best["val_cd_l2"],
        "val_f_score_at_the_best": best["val_f_score"],
        "val_cd_l2_by_tenth": [
            round(min(r["val_cd_l2"] for r in rows[i : i + max(1, len(rows) // 10)]), 3)
            for i in range(0, len(rows), max(1, len(rows) // 10))
        ],
        "target": args.target,
    }
    if oracle is not None:
        # another sample of the same surfaces, cut as the validation cuts
        report["surface_oracle"] = oracle
    print(json.dumps(report, indent=2))
    return 0 if report["val_cd_l2_best_last_tenth"] <= args.target else 1


if __name__ == "__main__":
    sys.exit(main())
