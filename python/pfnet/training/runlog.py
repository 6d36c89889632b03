"""The run folder's log and curves: ``log.jsonl`` (a row per epoch) and ``curves.png``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from pfnet.io.files import atomic_path


def write_log(path: Path, history: list[dict[str, Any]]) -> None:
    """Rewrite the per-epoch JSON-lines log."""
    with atomic_path(path) as tmp:
        tmp.write_text("".join(json.dumps(row) + "\n" for row in history))


def epoch_line(
    epoch: int, epochs: int, row: dict[str, Any], keys: tuple[str, ...], improved: bool
) -> str:
    """The line an epoch is shown by: ``epoch 3/10: loss_g 0.1, ... (best)``, of ``row``'s
    ``keys``."""
    shown = ", ".join(f"{k} {row[k]:.4g}" for k in keys if k in row)
    return f"epoch {epoch}/{epochs}: {shown}{' (best)' if improved else ''}"


def plot_curves(path: Path, history: list[dict[str, Any]]) -> None:
    """Plot training losses and validation Chamfer distances against the epoch."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt
    from matplotlib.ticker import MaxNLocator

    fig, (ax_loss, ax_val) = plt.subplots(1, 2, figsize=(10, 4))
    for key in ("loss_g", "cd_detail", "cd_secondary", "cd_primary", "loss_d", "adv_g"):
        points = [(r["epoch"], r[key]) for r in history if key in r]
        if points:
            ax_loss.plot(*zip(*points, strict=True), marker=".", label=key)
    ax_loss.set(xlabel="epoch", ylabel="training loss", title="Training losses")
    for key, label in (
        ("val_cd_l2", "CD-L2 (Pred→GT + GT→Pred)"),
        ("val_pred_to_gt", "Pred→GT"),
        ("val_gt_to_pred", "GT→Pred"),
        ("val_live_cd_l2", "CD-L2 of the live weights (with ema)"),
    ):
        points = [(r["epoch"], r[key]) for r in history if key in r]
        if points:
            ax_val.plot(*zip(*points, strict=True), marker=".", label=label)
    ax_val.set(xlabel="epoch", ylabel="×1000, missing region", title="Validation (test protocol)")
    for ax in (ax_loss, ax_val):
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        if ax.lines:
            ax.set_yscale("log")
            ax.legend(fontsize="small")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
