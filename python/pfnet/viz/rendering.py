"""Drawing point clouds the way the paper's figures do (the work behind ``pfnet render``).

The paper's completion figures show, per shape, the partial input in grey, the input merged
with the predicted missing region in yellow, and the ground truth in blue. A gallery here has
one row per sample and, for each of several viewing angles, up to three panels: *input*
(partial, grey), *completion* (partial grey + prediction yellow) and *ground truth* (blue).
Panels whose clouds are not given are left out.

:func:`render_gallery` draws samples of up to three clouds; :func:`render_panels`, the layout
of every gallery, is also behind :mod:`pfnet.viz.gallery` and the study's figures. The data sets
are y-up (ShapeNet, SweetHome3D), so the y axis is drawn vertical.
"""

from __future__ import annotations

import math
import os
import textwrap
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pfnet.errors import ConfigError, DataError
from pfnet.io.palette import GROUND_TRUTH_COLOR, PARTIAL_COLOR, PREDICTION_COLOR
from pfnet.viz.panels import Panel, column_titles


@dataclass
class RenderSample:
    """One gallery row: any of the three clouds may be absent.

    Attributes:
        label: Text drawn at the left of the row (e.g. ``"chair/chair_0003"``).
        partial: ``(P, 3)`` incomplete input, or None.
        prediction: ``(M, 3)`` predicted missing region (or a full completion), or None.
        ground_truth: ``(N, 3)`` complete cloud, or None.
        cloud: ``(K, 3)`` a cloud drawn in its own colours ``cloud_colors`` (a file that
            ``pfnet complete`` wrote, grey and yellow), or None.
        cloud_colors: ``(K, 3)`` float colours in ``[0, 1]`` of ``cloud``.
    """

    label: str
    partial: np.ndarray | None = None
    prediction: np.ndarray | None = None
    ground_truth: np.ndarray | None = None
    cloud: np.ndarray | None = None
    cloud_colors: np.ndarray | None = None


# A cloud with at most this many distinct colours is drawn as one layer per colour (so that
# the paper's colours get their legend names in the viewer); with more, one layer of colours.
MAX_COLOR_LAYERS = 16
OWN_COLORS_TITLE = "its own colours"


def _hex(color: np.ndarray) -> str:
    return "#" + "".join(f"{int(v):02x}" for v in color)


def own_color_panel(cloud: np.ndarray, colors: np.ndarray) -> Panel:
    """The panel of a cloud in its own per-point ``colors`` (``(K, 3)`` floats in ``[0, 1]``).

    Its title says what the colours are: a cloud in the paper's colours is titled as a
    gallery's panel would be (grey and yellow: ``completion``; yellow: ``prediction``; grey:
    ``input``; blue: ``ground truth``), any other ``its own colours``.
    """
    cloud, colors = np.asarray(cloud), np.asarray(colors, dtype=np.float64)
    if colors.shape != cloud.shape:
        raise DataError(f"colours of shape {colors.shape} for a cloud of shape {cloud.shape}")
    codes = np.rint(np.clip(colors, 0.0, 1.0) * 255).astype(np.uint8)
    distinct, first, inverse = np.unique(codes, axis=0, return_index=True, return_inverse=True)
    if len(distinct) > MAX_COLOR_LAYERS:
        return OWN_COLORS_TITLE, [(cloud, codes / 255.0)]
    inverse = inverse.reshape(-1)
    order = np.argsort(first)  # the colours in the file's order: grey (the scan) first
    layers = [(cloud[inverse == k], _hex(distinct[k])) for k in order]
    paper = {PARTIAL_COLOR: "input", PREDICTION_COLOR: "prediction"}
    names = {color for _, color in layers}
    if names == {PARTIAL_COLOR, PREDICTION_COLOR}:
        title = "completion"
    elif names == {GROUND_TRUTH_COLOR}:
        title = "ground truth"
    elif len(names) == 1 and next(iter(names)) in paper:
        title = paper[next(iter(names))]
    else:
        title = OWN_COLORS_TITLE
    return title, layers


def _panels(sample: RenderSample) -> list[tuple[str, list[tuple[np.ndarray, str]]]]:
    """The (title, [(points, colour), ...]) panels of one row, for one view."""
    panels = []
    if sample.partial is not None:
        panels.append(("input", [(sample.partial, PARTIAL_COLOR)]))
    if sample.prediction is not None:
        layers = [(sample.prediction, PREDICTION_COLOR)]
        if sample.partial is not None:
            layers.insert(0, (sample.partial, PARTIAL_COLOR))
        panels.append(("completion" if sample.partial is not None else "prediction", layers))
    if sample.ground_truth is not None:
        panels.append(("ground truth", [(sample.ground_truth, GROUND_TRUTH_COLOR)]))
    if sample.cloud is not None:
        if sample.cloud_colors is None:
            raise ConfigError(f"sample {sample.label!r} has a cloud without its colours")
        panels.append(own_color_panel(sample.cloud, sample.cloud_colors))
    return panels


def render_gallery(
    out: str | os.PathLike[str],
    samples: list[RenderSample],
    *,
    views: int = 2,
    title: str | None = None,
    point_size: float = 2.0,
    panel_inches: float = 2.2,
    dpi: int = 100,
) -> Path:
    """Draw ``samples`` into a PNG file, one row per sample, atomically.

    Each sample becomes the panels input / completion / ground truth (those it has); the
    other arguments, the return value and the errors are those of :func:`render_panels`.
    """
    if not samples:
        raise ConfigError("nothing to draw (no samples)")
    rows = []
    for sample in samples:
        panels = _panels(sample)
        if not panels:
            raise ConfigError(f"sample {sample.label!r} has no point cloud")
        rows.append((sample.label, panels))
    return render_panels(
        out,
        rows,
        views=views,
        title=title,
        point_size=point_size,
        panel_inches=panel_inches,
        dpi=dpi,
    )


def row_label(label: str, height_inches: float, fontsize: float) -> str:
    """``label`` broken into lines that fit beside a row ``height_inches`` tall.

    The category (before the first ``/``) gets a line of its own; a long name is wrapped (at
    hyphens where it can), so a label never runs into the rows above and below it.
    """
    # An average glyph of a sans-serif font is about 0.6 em wide.
    width = max(8, int(height_inches * 72 / (0.6 * fontsize)))
    head, slash, tail = label.partition("/")
    parts = [head + slash, tail] if slash else [label]
    lines = [line for part in parts for line in textwrap.wrap(part, width=width)]
    return "\n".join(lines)


# Views per row and rows per picture: a figure of more is too large to look at (and slow
# to draw: 1,000 rows took 44 s and 1.3 GB).
MAX_VIEWS = 12
MAX_ROWS = 200
# Points drawn per cloud and panel: more are not visible, only slow (5 M took minutes).
MAX_DRAWN = 50_000
# Marker area in points squared: larger markers cover the panel.
MAX_POINT_SIZE = 1000.0


def render_panels(
    out: str | os.PathLike[str],
    rows: list[tuple[str, list[Panel]]],
    *,
    views: int = 1,
    title: str | None = None,
    point_size: float = 2.0,
    panel_inches: float = 2.2,
    dpi: int = 100,
) -> Path:
    """Draw rows of labelled panels into a PNG file atomically (the layout of every gallery).

    Args:
        out: Destination ``.png`` path, or ``.html`` for :func:`pfnet.viz.viewer.write_viewer`
            (``views``, ``panel_inches`` and ``dpi`` then do not apply); its folder is
            created if needed.
        rows: ``(label, panels)`` per row. Each panel title is a column
            (:func:`column_titles`), headed by the title; a row without some panel leaves
            its cell empty. All panels of a row share one scale, so sizes compare across
            the row.
        views: Number of viewing angles per row (azimuths spread over 360 degrees).
        title: Optional figure title.
        point_size: Marker area in points squared.
        panel_inches: Size of one panel.
        dpi: Resolution of the PNG.

    Returns:
        The path written.

    Raises:
        ConfigError: If there are no rows or too many, a row has no panel, ``out`` is not a
            ``.png`` file, or ``views`` or ``point_size`` is out of range.
        DataError: If a cloud is not a finite ``(N, 3)`` array.
    """
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    from pfnet.io.files import atomic_path, output_path

    if not rows:
        raise ConfigError("nothing to draw (no samples)")
    if len(rows) > MAX_ROWS:
        raise ConfigError(
            f"{len(rows)} rows is more than the {MAX_ROWS} one picture can show; "
            "render them in several pictures"
        )
    suffix = Path(out).suffix.lower()
    if suffix not in (".png", ".html"):
        raise ConfigError(f"the picture must be a .png file (or .html), got {out}")
    if not 1 <= views <= MAX_VIEWS:
        raise ConfigError(f"views must be in [1, {MAX_VIEWS}], got {views}")
    if not (math.isfinite(point_size) and 0 < point_size <= MAX_POINT_SIZE):
        raise ConfigError(f"point size must be in (0, {MAX_POINT_SIZE:g}], got {point_size}")
    for label, panels in rows:
        if not panels:
            raise ConfigError(f"sample {label!r} has no point cloud")
        for _, layers in panels:
            for points, _color in layers:
                pts = np.asarray(points)
                if pts.ndim != 2 or pts.shape[1] != 3 or not np.isfinite(pts).all():
                    raise DataError(
                        f"sample {label!r} has a cloud of shape {pts.shape} "
                        "that is not a finite (N, 3) array"
                    )
    if suffix == ".html":  # the interactive viewer: the same rows, rotatable
        from pfnet.viz.viewer import write_viewer

        return write_viewer(out, rows, title=title, point_size=point_size)
    titles = column_titles(rows)
    n_cols = len(titles) * views
    # The title heads each column on the first row that has a panel in it.
    headed = {
        name: next(r for r, (_, ps) in enumerate(rows) if name in dict(ps)) for name in titles
    }
    fig = Figure(figsize=(panel_inches * n_cols + 0.6, panel_inches * len(rows) + 0.4), dpi=dpi)
    azimuths = [-60.0 + 360.0 * v / views for v in range(views)]
    for r, (label, panels) in enumerate(rows):
        everything = np.concatenate([np.asarray(p) for _, ls in panels for p, _ in ls])
        lo, hi = everything.min(axis=0), everything.max(axis=0)
        centre, half = (lo + hi) / 2.0, max(float((hi - lo).max()) / 2.0, 1e-9)
        for v, azimuth in enumerate(azimuths):
            for name, layers in panels:
                col = v * len(titles) + titles.index(name)
                ax = fig.add_subplot(len(rows), n_cols, r * n_cols + col + 1, projection="3d")
                for points, color in layers:
                    points = np.asarray(points)
                    if len(points) > MAX_DRAWN:  # a picture cannot show more; every k-th
                        step = -(-len(points) // MAX_DRAWN)
                        points = points[::step]
                        if not isinstance(color, str):  # one colour per point
                            color = np.asarray(color)[::step]
                    pts = np.asarray(points, dtype=np.float64) - centre
                    # y-up data: draw (x, z, y) so that y is matplotlib's vertical axis.
                    ax.scatter(
                        pts[:, 0],
                        pts[:, 2],
                        pts[:, 1],
                        s=point_size,
                        c=color,
                        depthshade=True,
                        linewidths=0,
                    )
                ax.set_xlim(-half, half)
                ax.set_ylim(-half, half)
                ax.set_zlim(-half, half)
                ax.set_box_aspect((1, 1, 1))
                ax.view_init(elev=20.0, azim=azimuth)
                ax.set_axis_off()
                if v == 0 and col == min(titles.index(n) for n, _ in panels):
                    ax.text2D(
                        0.0,
                        0.5,
                        row_label(label, panel_inches, fontsize=8),
                        transform=ax.transAxes,
                        rotation=90,
                        va="center",
                        ha="right",
                        fontsize=8,
                        multialignment="center",
                        parse_math=False,  # a "$" in a file or category name is text
                    )
                if r == headed[name]:
                    suffix = f" ({azimuth:.0f}°)" if views > 1 else ""
                    ax.set_title(name + suffix, fontsize=9, parse_math=False)
    # Inches kept free above the panels: the column titles, and the figure title above them.
    margin = 0.4 + (0.35 if title else 0.0)
    if title:
        fig.suptitle(
            title, fontsize=10, y=1.0 - 0.1 / fig.get_figheight(), va="top", parse_math=False
        )
    # Half an inch on the left for the row labels.
    fig.subplots_adjust(
        left=0.5 / fig.get_figwidth(),
        right=1.0,
        bottom=0.0,
        top=1.0 - margin / fig.get_figheight(),
    )
    out_path = output_path(out)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out_path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)
    return Path(out)
