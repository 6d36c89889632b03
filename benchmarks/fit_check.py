"""Fit check: can a generator memorise a handful of training shapes with pfnet's own loop?

A model that cannot fit 16 shapes cannot be compared with anything. This script takes the
first ``--shapes`` training shapes of a prepared data set (spread over its categories),
makes them both the train and the val split of a scratch data set, trains on them with
``pfnet train``'s loop for ``--steps`` optimiser steps, and reports the training Chamfer and
the validation CD-L2 ×1000 on the same shapes (test protocol, eval mode) over the run::

    python benchmarks/fit_check.py --data data/sh3d --out runs/fit [--model pfnet-vanilla]
        [--shapes 16] [--batch-size 16] [--lr 1e-3] [--steps 2000] [--milestones 0.5 0.75]
        [--target 1.0] [--config KEYS.toml]

The run is sized in steps (``--steps``) with the learning rate multiplied by the preset's
``lr_gamma`` at ``--milestones`` (fractions of the run; none for a constant rate).

It exits with 0 when the best validation CD-L2 of the last tenth of the run is at most
``--target``, else 1. Re-running with the same ``--out`` resumes the run.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from pfnet.data.format import CloudSet, load_split, read_manifest, split_record, write_dataset
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
    run = args.out / "run"
    resume = (run / "last.pt").is_file()
    train(config, data, run, device=args.device, resume=resume, progress=sys.stderr.isatty())
    rows = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()][1:]
    tail = rows[-max(1, len(rows) // 10) :]
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
        "val_cd_l2_best_last_tenth": min(r["val_cd_l2"] for r in tail),
        "val_cd_l2_by_tenth": [
            round(min(r["val_cd_l2"] for r in rows[i : i + max(1, len(rows) // 10)]), 3)
            for i in range(0, len(rows), max(1, len(rows) // 10))
        ],
        "target": args.target,
    }
    print(json.dumps(report, indent=2))
    return 0 if report["val_cd_l2_best_last_tenth"] <= args.target else 1


if __name__ == "__main__":
    sys.exit(main())
