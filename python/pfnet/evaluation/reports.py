"""An evaluation as text and files: the paper's table, the ``--csv`` per-sample scores and the
``--json`` report (schema in the README)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

from pfnet.evaluation.scoring import SCALE, Evaluation


def format_table(evaluation: Evaluation, summary: dict | None = None) -> str:
    """The paper-like table: per category Pred→GT / GT→Pred ×1000, n, CD-L2, CD-L1, F-score."""
    from pfnet.evaluation.metrics import summarize

    summary = summary or summarize(evaluation.per_sample, evaluation.categories, scale=float(SCALE))
    header = (
        f"{'category':<16} {'n':>5} {'Pred→GT':>9} {'GT→Pred':>9} "
        f"{'CD-L2':>9} {'CD-L1':>9} {'F@0.01':>7}"
    )
    lines = [header, "-" * len(header)]

    def row(name: str, n: str, m: dict) -> str:
        return (
            f"{name:<16} {n:>5} {m['pred_to_gt']:>9.3f} {m['gt_to_pred']:>9.3f} "
            f"{m['cd_l2']:>9.3f} {m['cd_l1'] * SCALE:>9.3f} {m['f_score']:>7.3f}"
        )

    for cat in sorted(summary["categories"]):
        m = summary["categories"][cat]
        lines.append(row(cat, str(int(m["n"])), m))
    lines.append("-" * len(header))
    lines.append(row("mean", str(len(evaluation.categories)), summary["mean"]))
    return "\n".join(lines)


def format_benchmark_table(report: dict) -> str:
    """A benchmark protocol's table (:func:`pfnet.evaluation.benchmarks.evaluate_benchmark`):
    per category CD-L1, CD-L2, Pred→GT, GT→Pred ×1000 and the F-score, then the unweighted
    mean; ShapeNet synset ids are shown with their names."""
    from pfnet.data.categories import category_title

    header = (
        f"{'category':<21} {'n':>6} {'CD-L1':>9} {'CD-L2':>9} {'Pred→GT':>9} "
        f"{'GT→Pred':>9} {'F@0.01':>7}"
    )
    lines = [header, "-" * len(header)]

    def row(name: str, n: object, m: dict) -> str:
        return (
            f"{name:<21} {n!s:>6} {m['cd_l1']:>9.3f} {m['cd_l2']:>9.3f} "
            f"{m['pred_to_gt']:>9.3f} {m['gt_to_pred']:>9.3f} {m['f_score']:>7.3f}"
        )

    for cat, m in sorted(report["categories"].items()):
        lines.append(row(category_title(cat), m["n"], m))
    lines.append("-" * len(header))
    total = sum(m["n"] for m in report["categories"].values())
    lines.append(row("mean", total, report["mean"]))
    return "\n".join(lines)


def format_kitti_table(report: dict) -> str:
    """The ``kitti`` protocol's table (:func:`pfnet.evaluation.benchmarks.evaluate_kitti`): per
    category Fidelity and MMD ×1000, then the unweighted mean."""
    header = f"{'category':<16} {'n':>6} {'Fidelity':>9} {'MMD':>9}"
    lines = [header, "-" * len(header)]
    for cat, m in sorted(report["categories"].items()):
        lines.append(f"{cat:<16} {m['n']:>6} {m['fidelity']:>9.3f} {m['mmd']:>9.3f}")
    lines.append("-" * len(header))
    total = sum(m["n"] for m in report["categories"].values())
    mean = report["mean"]
    lines.append(f"{'mean':<16} {total:>6} {mean['fidelity']:>9.3f} {mean['mmd']:>9.3f}")
    return "\n".join(lines)


def write_kitti_csv(path: Path, evaluation: Evaluation) -> None:
    """Per-car scores of the ``kitti`` protocol: category, name, Fidelity and MMD ×1000, and
    the reference car nearest the completion (``<split>/<name>`` in the reference set)."""
    from pfnet.io.files import atomic_path

    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="", encoding="utf-8") as fh:
            writer = csv.writer(fh)
            writer.writerow(["category", "name", "fidelity", "mmd", "nearest_reference"])
            ps, nearest = evaluation.per_sample, evaluation.labels["nearest_reference"]
            for i, (cat, name) in enumerate(
                zip(evaluation.categories, evaluation.names, strict=True)
            ):
                values = [f"{ps[k][i] * SCALE:.6f}" for k in ("fidelity", "mmd")]
                writer.writerow([cat, name, *values, nearest[i]])


def write_csv(path: Path, evaluation: Evaluation) -> None:
    """Per-sample scores: category, name and the metrics (×1000 except the F-score)."""
    from pfnet.io.files import atomic_path

    keys = ("pred_to_gt", "gt_to_pred", "cd_l2", "cd_l1")  # every one ×1000 here
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="", encoding="utf-8") as fh:
            writer = csv.writer(fh)
            writer.writerow(["category", "name", *keys, "f_score"])
            ps = evaluation.per_sample
            for i, (cat, name) in enumerate(
                zip(evaluation.categories, evaluation.names, strict=True)
            ):
                values = [f"{ps[k][i] * SCALE:.6f}" for k in keys]
                writer.writerow([cat, name, *values, f"{ps['f_score'][i]:.6f}"])


def write_json(path: Path, report: dict) -> None:
    """Write the ``--json`` report atomically."""
    from pfnet.io.files import atomic_path

    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
