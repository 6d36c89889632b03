"""Galleries of completions: test samples' input, one or more models' completions, ground
truth, in the paper's colours (one builder for ``predict``, ``evaluate`` and ``demo``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pfnet.errors import DataError


def pick_gallery(categories: list[str], count: int) -> list[int]:
    """Indices of up to ``count`` samples taken round-robin over the categories (sorted)."""
    by_cat: dict[str, list[int]] = {}
    for i, cat in enumerate(categories):
        by_cat.setdefault(cat, []).append(i)
    queues = [by_cat[c] for c in sorted(by_cat)]
    picked: list[int] = []
    depth = 0
    while len(picked) < count and any(depth < len(q) for q in queues):
        picked += [q[depth] for q in queues if depth < len(q)][: count - len(picked)]
        depth += 1
    return picked


def render_completions(
    out: Path,
    data_dir: Path,
    columns: dict[str, Path],
    *,
    split: str,
    missing_ratio: float,
    keys: list[tuple[str, str]],
    title: str,
) -> Path:
    """Render the samples ``keys`` (``(category, name)``) of ``split``, one row each.

    Each row shows the test-protocol input, the completion of every prediction folder in
    ``columns`` (title -> folder) and the ground truth; one folder gets two views per row.

    Raises:
        DataError: A folder has no prediction for a sample.
    """
    from pfnet.data import load_split, test_protocol_crop
    from pfnet.evaluation import find_prediction_files
    from pfnet.io import read_point_cloud
    from pfnet.rendering import GROUND_TRUTH_COLOR, PARTIAL_COLOR, PREDICTION_COLOR, render_panels

    clouds = load_split(data_dir, split)
    index = {
        (str(c), str(n)): i
        for i, (c, n) in enumerate(zip(clouds.category, clouds.name, strict=True))
    }
    points = np.asarray(clouds.points)
    # Crop the whole split: sample i's viewpoint depends on its index in the split.
    partial, _ = test_protocol_crop(points, missing_ratio)
    files = {column: find_prediction_files(folder) for column, folder in columns.items()}
    rows = []
    for category, name in keys:
        i, key = index[(category, name)], f"{category}/{name}"
        panels = [("input", [(partial[i], PARTIAL_COLOR)])]
        for column, found in files.items():
            if key not in found:
                raise DataError(f"{columns[column]} has no prediction for {key}")
            completion = read_point_cloud(found[key])
            panels.append((column, [(partial[i], PARTIAL_COLOR), (completion, PREDICTION_COLOR)]))
        panels.append(("ground truth", [(points[i], GROUND_TRUTH_COLOR)]))
        rows.append((key, panels))
    return render_panels(out, rows, views=2 if len(columns) == 1 else 1, title=title)


def render_prediction_gallery(
    out: Path, pred_dir: Path, data_dir: Path, *, split: str, missing_ratio: float, count: int
) -> Path:
    """Render ``count`` predicted samples (spread over the categories) as partial/pred/gt rows."""
    from pfnet.data import load_split

    clouds = load_split(data_dir, split)
    categories = [str(c) for c in clouds.category]
    keys = [(categories[i], str(clouds.name[i])) for i in pick_gallery(categories, count)]
    title = f"{Path(pred_dir).name}: {split}, {missing_ratio:.0%} missing"
    return render_completions(
        out,
        data_dir,
        {"completion": Path(pred_dir)},
        split=split,
        missing_ratio=missing_ratio,
        keys=keys,
        title=title,
    )
