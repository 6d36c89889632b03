"""Combining a study's runs over seeds into one record per setting."""

from __future__ import annotations

import math
from typing import Any

import numpy as np


def _summary(report: dict[str, Any]) -> dict[str, Any]:
    """The per-category and mean metrics of an evaluation report."""
    return {"categories": report["categories"], "mean": report["mean"]}


def _mean_metrics(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Key-wise mean of metric dicts; the sample count ``n`` is the same in each and kept."""
    return {k: (rows[0][k] if k == "n" else float(np.mean([r[k] for r in rows]))) for k in rows[0]}


def _region_over_seeds(runs: list[dict[str, Any]], region: str) -> dict[str, Any]:
    """One region's metrics of the seeds of a setting: means, and the spread of the mean row."""
    categories = runs[0][region]["categories"]
    means = [r[region]["mean"] for r in runs]
    return {
        "categories": {
            c: _mean_metrics([r[region]["categories"][c] for r in runs]) for c in categories
        },
        "mean": _mean_metrics(means),
        # Sample standard deviation over seeds of the mean over categories (None for one seed).
        "std": {
            k: (float(np.std([m[k] for m in means], ddof=1)) if len(means) > 1 else None)
            for k in means[0]
        },
    }


def _gain_or_lowest(gain: float | None) -> float:
    return -math.inf if gain is None else gain


def summarize_settings(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The runs of each setting (model, missing ratio) combined over their seeds.

    Args:
        runs: Run records (``evaluate_run``), any number of seeds per setting.

    Returns:
        One record per setting, in order of first appearance: the metrics of both regions
        averaged over the seeds (with ``std``, the spread over seeds of the overall mean),
        training time summed over the seeds, the median epoch time, each seed's best epoch,
        the mean best validation CD-L2, and the plateau check of the seed that improved most
        in its last quarter (``levelled`` only when every seed levelled off).
    """
    groups: dict[str, list[dict[str, Any]]] = {}
    for run in runs:
        groups.setdefault(run["setting"], []).append(run)
    settings = []
    for name, group in groups.items():
        first = group[0]
        worst = max(group, key=lambda r: _gain_or_lowest(r["plateau"]["gain"]))
        settings.append(
            {
                "name": name,
                "model": first["model"],
                "missing_ratio": first["missing_ratio"],
                "n_missing": first["n_missing"],
                "parameters": first["parameters"],
                "seeds": [r["seed"] for r in group],
                "epochs": first["epochs"],
                "train_time_s": round(sum(r["train_time_s"] for r in group), 1),
                "epoch_time_s": round(float(np.median([r["epoch_time_s"] for r in group])), 2),
                "best_epochs": [r["best_epoch"] for r in group],
                "best_val_cd_l2": float(np.mean([r["best_val_cd_l2"] for r in group])),
                "plateau": {
                    **worst["plateau"],
                    "seed": worst["seed"],
                    "levelled": all(r["plateau"]["levelled"] for r in group),
                },
                "missing": _region_over_seeds(group, "missing"),
                "whole": _region_over_seeds(group, "whole"),
            }
        )
    return settings
