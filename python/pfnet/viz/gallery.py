"""Galleries of completions: test samples' input, one or more models' completions, ground
truth, in the paper's colours (one builder for ``predict``, ``evaluate`` and ``demo``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pfnet.errors import DataError
from pfnet.evaluation.scoring import Evaluation

DEFAULT_ROWS = 8
"""Rows of a ``--gallery`` when ``--gallery-count`` is not given."""


def check_gallery_options(gallery: Path | None, count: int | None) -> int:
    """The rows of ``--gallery`` (``--gallery-count``, default :data:`DEFAULT_ROWS`), checked
    before any work (1,000 rows once failed after every prediction was made).

    Raises:
        ConfigError: A count outside [1, ``MAX_ROWS``] or without ``--gallery``, or a
            gallery that is not a ``.png`` or ``.html`` file.
    """
    from pfnet.errors import ConfigError
    from pfnet.viz.rendering import MAX_ROWS

    if gallery is None:
        if count is not None:
            raise ConfigError("--gallery-count applies only with --gallery")
        return DEFAULT_ROWS
    count = DEFAULT_ROWS if count is None else count
    if not 1 <= count <= MAX_ROWS:
        raise ConfigError(f"--gallery-count must be in [1, {MAX_ROWS}], got {count}")
    if Path(gallery).suffix.lower() not in (".png", ".html"):
        raise ConfigError(f"--gallery must be a .png file (or .html), got {gallery}")
    return count


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
    from pfnet.evaluation.scoring import find_prediction_files
    from pfnet.io.clouds import read_point_cloud
    from pfnet.io.palette import GROUND_TRUTH_COLOR, PARTIAL_COLOR, PREDICTION_COLOR
    from pfnet.viz.rendering import render_panels

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


def pick_benchmark_gallery(keys: list[str], count: int, views: int) -> list[str]:
    """Up to ``count`` of the prediction keys ``<category>/<stem>`` spread over the
    categories, one view per shape (ShapeNet-55's ``<name>_view<v>``: shape j shows view
    ``j % views`` when it was scored, else its first scored view)."""
    if views > 1:
        by_shape: dict[str, dict[int, str]] = {}
        for key in keys:
            shape, _, view = key.rpartition("_view")
            by_shape.setdefault(shape, {})[int(view)] = key
        keys = []
        for j, found in enumerate(by_shape.values()):
            keys.append(found.get(j % views) or found[min(found)])
    chosen = pick_gallery([key.split("/", 1)[0] for key in keys], count)
    return [keys[i] for i in chosen]


def render_benchmark_gallery(
    out: Path,
    pred_dir: Path,
    data_dir: Path,
    protocol: str,
    *,
    keys: list[str],
    count: int,
    split: str,
    missing_ratio: float | None,
    nearest: dict[str, str] | None = None,
    references: Path | None = None,
    reference_category: str = "car",
) -> Path:
    """Render ``count`` of the completions ``keys`` (``<category>/<stem>``; picked by
    :func:`pick_benchmark_gallery`) of a benchmark protocol (``pcn``, ``shapenet55``,
    ``kitti``), one row each: the protocol's input (PCN's scan,
    PoinTr's 2,048-point crop, the KITTI car in its object frame), the whole completion,
    and the ground truth (the complete cloud; for KITTI the reference car nearest the
    completion, ``nearest`` (key -> ``<split>/<name>`` of ``references``), when given).

    Raises:
        DataError: A prediction is missing or unreadable.
    """
    from pfnet.data import load_split
    from pfnet.data.categories import category_title
    from pfnet.evaluation.benchmarks import load_references
    from pfnet.evaluation.protocols import get_protocol, shapenet_crop
    from pfnet.evaluation.scoring import find_prediction_files
    from pfnet.io.clouds import read_point_cloud
    from pfnet.io.palette import GROUND_TRUTH_COLOR, PARTIAL_COLOR, PREDICTION_COLOR
    from pfnet.viz.rendering import render_panels

    chosen = get_protocol(protocol)
    keys = pick_benchmark_gallery(keys, count, chosen.views)
    clouds = load_split(data_dir, split)
    index = {
        f"{c}/{n}": i for i, (c, n) in enumerate(zip(clouds.category, clouds.name, strict=True))
    }
    partials = boxes = None
    if chosen.input == "given":
        from pfnet.data.benchmarks import load_partials

        partials = load_partials(data_dir, split, len(clouds))
    if chosen.name == "kitti":
        from pfnet.data.kitti import load_boxes

        boxes = load_boxes(data_dir, split, len(clouds))
    cars: dict[str, np.ndarray] = {}
    if nearest and references is not None:
        refs, labels = load_references(references, reference_category)
        wanted = {nearest[k] for k in keys if k in nearest}
        cars = {label: refs[i] for i, label in enumerate(labels) if label in wanted}
    files = find_prediction_files(pred_dir)
    rows = []
    for key in keys:
        if key not in files:
            raise DataError(f"{pred_dir} has no prediction for {key}")
        shape, view = key, 0
        if chosen.views > 1:
            shape, _, v = key.rpartition("_view")
            view = int(v)
        i = index[shape]
        if chosen.name == "kitti":
            from pfnet.data.kitti import kitti_input

            given = kitti_input(partials[i], boxes[i], key)
        elif partials is not None:
            given = partials[i]
        else:
            given = shapenet_crop(np.asarray(clouds.points[i]), missing_ratio, view)
        completion = read_point_cloud(files[key])
        panels = [
            ("input", [(given, PARTIAL_COLOR)]),
            ("completion", [(completion, PREDICTION_COLOR)]),
        ]
        if chosen.name != "kitti":
            panels.append(("ground truth", [(np.asarray(clouds.points[i]), GROUND_TRUTH_COLOR)]))
        elif cars:
            panels.append(("nearest reference", [(cars[nearest[key]], GROUND_TRUTH_COLOR)]))
        category, _, stem = key.partition("/")
        rows.append((f"{category_title(category)}/{stem}", panels))
    shown = "" if missing_ratio is None else f", {missing_ratio:.0%} missing"
    title = f"{Path(pred_dir).name}: {chosen.name}, {split}{shown}"
    return render_panels(out, rows, views=1, title=title)


def render_evaluation_gallery(
    out: Path,
    evaluation: Evaluation,
    pred_dir: Path,
    data_dir: Path,
    *,
    split: str,
    missing_ratio: float,
    count: int,
    columns: dict[str, Path] | None = None,
) -> Path:
    """Render ``count`` scored samples (spread over the categories) as partial/pred/gt rows.

    ``columns`` (title -> prediction folder) draws several models' completions of the same
    samples side by side instead of ``pred_dir``'s alone.
    """
    chosen = pick_gallery(evaluation.categories, count)
    return render_completions(
        out,
        data_dir,
        columns or {"completion": pred_dir},
        split=split,
        missing_ratio=missing_ratio,
        keys=[(evaluation.categories[k], evaluation.names[k]) for k in chosen],
        title=f"{pred_dir.name}: {split}, {missing_ratio:.0%} missing",
    )
