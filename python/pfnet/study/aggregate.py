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
                **({"steps": first["steps"]} if "steps" in first else {}),
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


def twice_the_steps(settings: list[dict[str, Any]], tolerance: float) -> dict[str, Any]:
    """The twice-the-steps test of a study sized in steps, and the length its tables show.

    For each model and missing ratio, its settings of increasing length (in steps) are
    compared in turn: a length is *converged* when the next one's best validation CD-L2 (mean
    over seeds) is not lower by more than ``tolerance`` (a fraction). The tables compare the
    models at one length, as the paper trains them all alike: the shortest length at which
    every setting is converged, or the longest if there is none.

    Returns:
        ``lengths`` (the study's run lengths, increasing), ``shown`` (the length the tables
        show), ``all_converged`` (whether every setting passed the test at it) and
        ``entries``: one per model and ratio, in order of first appearance, with ``lengths``
        (its settings by length), ``gains`` (for each length but the last, the relative
        validation gain of the next one; positive: the longer run is better) and
        ``converged`` (for each length but the last, whether it passed).
    """
    groups: dict[tuple[str, float], list[dict[str, Any]]] = {}
    for setting in settings:
        groups.setdefault((setting["model"], setting["missing_ratio"]), []).append(setting)
    entries = []
    for group in groups.values():
        by_length = sorted(group, key=lambda s: s.get("steps") or 0)
        gains = [
            (a["best_val_cd_l2"] - b["best_val_cd_l2"]) / a["best_val_cd_l2"]
            for a, b in zip(by_length, by_length[1:], strict=False)
        ]
        entries.append(
            {
                "lengths": by_length,
                "gains": gains,
                "converged": [gain <= tolerance for gain in gains],
            }
        )
    lengths = sorted({s.get("steps") or 0 for s in settings})
    passed = [
        k
        for k in range(len(lengths) - 1)
        if all(len(e["converged"]) > k and e["converged"][k] for e in entries)
    ]
    shown = passed[0] if passed else len(lengths) - 1
    return {
        "lengths": lengths,
        "shown": lengths[shown],
        "all_converged": bool(passed),
        "entries": entries,
    }


def reported_settings(settings: list[dict[str, Any]], tolerance: float) -> list[dict[str, Any]]:
    """The settings the tables and figures show: all of them, or in a study sized in steps
    those of the length :func:`twice_the_steps` picks."""
    if not any("steps" in s for s in settings):
        return settings
    shown = twice_the_steps(settings, tolerance)["shown"]
    return [s for s in settings if s.get("steps") == shown]
