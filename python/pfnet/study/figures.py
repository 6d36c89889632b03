"""The study's figures: validation curves of every run, one gallery of every model."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from pfnet.models.registry import MODEL_TITLES
from pfnet.study.aggregate import reported_settings
from pfnet.study.runs import BASE_RATIO, CONVERGENCE_TOLERANCE


def plot_curves(path: Path, results: dict[str, Any]) -> Path:
    """Validation CD-L2 per epoch of every setting: the ablation left, the ratios right.

    Each setting is drawn as the mean over its seeds with the band between the lowest and the
    highest seed; a dot marks each seed's best epoch (the checkpoint that was tested).
    """
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    from pfnet.io.files import atomic_path

    fig = Figure(figsize=(10, 3.6), dpi=90)
    axes = fig.subplots(1, 2)
    settings = reported_settings(results["settings"], CONVERGENCE_TOLERANCE)
    groups = (
        (
            "missing 25 %: the five models",
            [s for s in settings if s["missing_ratio"] == BASE_RATIO],
            "model",
        ),
        ("PF-Net: missing ratio", [s for s in settings if s["model"] == "pfnet"], "ratio"),
    )
    n_seeds = len(results["seeds"])
    for ax, (title, group, key) in zip(axes, groups, strict=True):
        for setting in group:
            runs = [r for r in results["runs"] if r["setting"] == setting["name"]]
            length = min(len(r["curve"]["epoch"]) for r in runs)
            epochs = runs[0]["curve"]["epoch"][:length]
            curves = np.array([r["curve"]["val_cd_l2"][:length] for r in runs])
            label = (
                MODEL_TITLES[setting["model"]]
                if key == "model"
                else (f"{setting['missing_ratio']:.0%}")
            )
            line = ax.plot(epochs, curves.mean(axis=0), label=label, lw=1.2)[0]
            if len(runs) > 1:
                ax.fill_between(
                    epochs,
                    curves.min(axis=0),
                    curves.max(axis=0),
                    color=line.get_color(),
                    alpha=0.2,
                )
            for r in runs:
                ax.plot(r["best_epoch"], r["best_val_cd_l2"], "o", color=line.get_color(), ms=2.5)
        ax.set_yscale("log")
        ax.set_xlabel("epoch")
        ax.set_ylabel("validation CD-L2 ×1000 (missing region)")
        ax.set_title(
            title + (f" (mean of {n_seeds} seeds, band: min-max)" if n_seeds > 1 else ""),
            fontsize=9,
        )
        ax.grid(True, which="both", alpha=0.3)
        if group:  # a study without PF-Net has no ratio curves
            ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path


def render_comparison(
    path: Path, results: dict[str, Any], runs_dir: Path, data_dir: Path, count: int
) -> Path | None:
    """The same test shapes (25 % missing) completed by each model, ground truth last."""
    from pfnet.data import load_split, test_protocol_crop
    from pfnet.io.clouds import read_point_cloud
    from pfnet.io.palette import GROUND_TRUTH_COLOR, PARTIAL_COLOR, PREDICTION_COLOR
    from pfnet.viz.gallery import pick_gallery
    from pfnet.viz.rendering import render_panels

    # One seed's predictions (the first): an average of seeds is no one model's output.
    seed = results["seeds"][0]
    shown = {s["name"] for s in reported_settings(results["settings"], CONVERGENCE_TOLERANCE)}
    runs = [
        r
        for r in results["runs"]
        if r["missing_ratio"] == BASE_RATIO and r["seed"] == seed and r["setting"] in shown
    ]
    if not runs or count < 1:
        return None
    clouds = load_split(data_dir, "test")
    points = np.asarray(clouds.points)
    partial, _ = test_protocol_crop(points, BASE_RATIO)
    categories = [str(c) for c in clouds.category]
    rows = []
    for i in pick_gallery(categories, count):
        key = f"{categories[i]}/{clouds.name[i]}"
        panels = [("input", [(partial[i], PARTIAL_COLOR)])]
        for run in runs:
            pred = read_point_cloud(runs_dir / run["name"] / "predictions" / f"{key}.npy")
            panels.append(
                (
                    MODEL_TITLES[run["model"]],
                    [(partial[i], PARTIAL_COLOR), (pred, PREDICTION_COLOR)],
                )
            )
        panels.append(("ground truth", [(points[i], GROUND_TRUTH_COLOR)]))
        rows.append((key, panels))
    return render_panels(
        path,
        rows,
        views=1,
        title="test split, 25 % missing: input grey, predicted missing region yellow",
        point_size=1.5,
        panel_inches=1.7,
        dpi=72,
    )
