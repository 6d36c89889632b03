"""Training and validation curves of several runs in one picture, from their ``log.jsonl``.

    python benchmarks/run_curves.py runs/aligned-ft2-3600 runs/mirror-ft-3600 \\
        --out docs/mirror-curves.png [--label NAME ...]

Left: validation CD-L2 ×1000 (the run's own validation, after every epoch) against the
optimiser step, with the median of the last :data:`WINDOW` epochs (a validation split of a few
dozen scans jumps by half from one epoch to the next at a full learning rate, so its running
best is a lucky epoch, not a level); right: the training loss's detail Chamfer term. A run
still going is drawn as far as its log goes.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def read_log(run: Path) -> list[dict]:
    """The rows of ``run/log.jsonl`` (a row cut short by a kill is left out)."""
    rows = []
    for line in (run / "log.jsonl").read_text(encoding="utf-8").splitlines():
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return rows


WINDOW = 10
"""Epochs in the validation's running median."""


def running_median(values: list[float], window: int = WINDOW) -> list[float]:
    """The median of each value and the ``window - 1`` before it (fewer at the start)."""
    import numpy as np

    return [float(np.median(values[max(0, k - window + 1) : k + 1])) for k in range(len(values))]


def curves(rows: list[dict]) -> dict[str, list[tuple[int, float]]]:
    """``{"val": [(step, val_cd_l2)], "train": [(step, cd_detail)]}`` of one run's rows."""
    val = [(int(r.get("step", 0)), float(r["val_cd_l2"])) for r in rows if "val_cd_l2" in r]
    train = [(int(r["step"]), float(r["cd_detail"])) for r in rows if "cd_detail" in r]
    return {"val": val, "train": train}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run folders of pfnet train")
    parser.add_argument("--out", type=Path, required=True, help="the .png to write")
    parser.add_argument("--label", action="append", help="a name per run (default: folder)")
    args = parser.parse_args(argv)
    labels = args.label or [run.name for run in args.runs]
    if len(labels) != len(args.runs):
        parser.error(f"{len(labels)} --label for {len(args.runs)} runs")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
    for run, label in zip(args.runs, labels, strict=True):
        found = curves(read_log(run))
        if found["val"]:
            steps, values = zip(*found["val"], strict=True)
            (line,) = left.plot(steps, values, alpha=0.35, label=f"{label} (each epoch)")
            level = running_median(list(values))
            left.plot(steps, level, color=line.get_color(), label=f"{label} (median of {WINDOW})")
        if found["train"]:
            steps, values = zip(*found["train"], strict=True)
            right.plot(steps, values, label=label)
    left.set(xlabel="optimiser step", ylabel="val CD-L2 x1000", yscale="log")
    left.set_title("validation")
    right.set(xlabel="optimiser step", ylabel="training cd_detail (its Chamfer terms x loss scale)")
    right.set_title("training")
    left.legend(fontsize=7)
    right.legend(fontsize=7)
    figure.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
