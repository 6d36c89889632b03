"""Training beside validation and test for finished runs: table rows and curves.

    python benchmarks/small_data_runs.py results/small-data/gpu-D-* --plot curves.png

Each argument is a run folder holding ``config.json`` and ``log.jsonl`` of ``pfnet train``
and, if scored, ``eval-test-best.json`` / ``eval-test-last.json`` (``pfnet evaluate --json``
of ``best.pt``'s and the last weights' predictions of the test split). Training is the
training Chamfer over the last tenth of the run (random crops; ``cd_detail`` is
``loss_scale`` · (Pred→GT + GT→Pred), so ×1000 / ``loss_scale`` gives CD-L2 ×1000);
validation is the val split under the test protocol: CD-L2 ×1000 (mean of the last tenth,
and best) and missing-region F-score@0.01 (mean of the last tenth). Training and
validation are CD-L2 whatever loss (``chamfer``) the run trained on. A run trained with
``--ema`` gets a second row, "(live weights)": the validation of the weights the optimiser
trained (``val_live_*``) beside that of their average (``val_*``), one trajectory.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def summarise(run: Path, live: bool = False) -> dict:
    """The figures of one run folder (``live``: of its live weights, with ``--ema``)."""
    config = json.loads((run / "config.json").read_text())
    lines = (run / "log.jsonl").read_text().splitlines()
    rows = [r for r in map(json.loads, lines) if "step" in r]
    if live:  # the live weights' validation under the names of the scored one's
        rows = [
            {**r, **{"val_" + k[9:]: v for k, v in r.items() if k[:9] == "val_live_"}} for r in rows
        ]
    tail = rows[-max(1, len(rows) // 10) :]
    best = min(rows, key=lambda r: r["val_cd_l2"])
    summary = {
        "run": run.name + (" (live weights)" if live else ""),
        "steps": rows[-1]["step"],
        "width": config["width"],
        "seed": config["seed"],
        "train": sum(r["cd_detail"] for r in tail) / len(tail) * 1000 / config["loss_scale"],
        "val_last_tenth": sum(r["val_cd_l2"] for r in tail) / len(tail),
        "val_best": best["val_cd_l2"],
        "val_best_step": best["step"],
        "val_f_last_tenth": sum(r["val_f_score"] for r in tail) / len(tail),
        "loss": config.get("chamfer", "l2"),
        "curve": [
            (r["step"], r["cd_detail"] * 1000 / config["loss_scale"], r["val_cd_l2"]) for r in rows
        ],
    }
    for which in ("best", "last"):
        path = run / f"eval-test-{which}.json"
        if path.is_file() and not live:
            report = json.loads(path.read_text())
            mean = report["mean"]
            summary[f"test_{which}"] = mean["pred_to_gt"] + mean["gt_to_pred"]
            summary[f"f_{which}"] = mean["f_score"]
    return summary


def table_row(s: dict) -> str:
    """One markdown row: run, loss, steps, training, val (CD-L2 last tenth and best, F-score
    last tenth), test CD-L2 and F-score."""
    test = " / ".join(f"{s[k]:.2f}" for k in ("test_best", "test_last") if k in s) or "—"
    f_score = " / ".join(f"{s[k]:.3f}" for k in ("f_best", "f_last") if k in s) or "—"
    return (
        f"| {s['run']} | {s['loss']} | {s['steps']:,} | {s['train']:.2f} | "
        f"{s['val_last_tenth']:.2f} | {s['val_best']:.2f} (step {s['val_best_step']:,}) | "
        f"{s['val_f_last_tenth']:.3f} | {test} | {f_score} |"
    )


def plot(summaries: list[dict], out: Path) -> None:
    """Training and validation CD-L2 against steps, one line per run."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (train_ax, val_ax) = plt.subplots(1, 2, figsize=(10, 3.6))
    for s in summaries:
        steps, train, val = zip(*s["curve"])
        label = f"{s['run']} ({s['loss']}, width {s['width']}, seed {s['seed']})"
        train_ax.plot(steps, train, lw=1, label=label)
        val_ax.plot(steps, val, lw=1, label=label)
    for ax, title, ylabel in (
        (train_ax, "Training", "training CD-L2 ×1000 (random crops)"),
        (val_ax, "Validation (26 shapes)", "val CD-L2 ×1000 (test protocol)"),
    ):
        ax.set(title=title, xlabel="optimiser step", ylabel=ylabel, yscale="log", ylim=(4, 30))
        ax.xaxis.set_major_formatter(lambda x, _: f"{x / 1000:g}k")
        ax.yaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
        ax.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_yticks([4, 5, 6, 8, 10, 15, 20, 30])
        ax.grid(alpha=0.3)
    val_ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=100)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("runs", type=Path, nargs="+", help="run folders")
    parser.add_argument("--plot", type=Path, help="write the curves to this PNG")
    args = parser.parse_args(argv)
    summaries = []
    for run in args.runs:
        summaries.append(summarise(run))
        if "val_live_cd_l2" in (run / "log.jsonl").read_text():
            summaries.append(summarise(run, live=True))
    print(
        "| run | loss | steps | training | val, last tenth | val, best | val F-score, last tenth "
        "| test CD-L2 (best / last) | test F-score (best / last) |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for s in summaries:
        print(table_row(s))
    if args.plot:
        plot(summaries, args.plot)
        print(f"wrote {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
