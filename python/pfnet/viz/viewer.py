"""An interactive gallery: one self-contained HTML file (plotly, its JavaScript inlined).

The same rows of panels as the PNG galleries (:func:`pfnet.viz.rendering.render_panels`): per
sample, the panels *input* (grey), *completion* (grey + yellow) and *ground truth* (blue),
side by side, each a rotatable 3D scene (drag to turn, scroll to zoom). A menu picks the
sample; the legend has one entry per layer (partial input, prediction, ground truth) that
shows or hides it in every panel.

One sample is shown at a time because every 3D scene is a WebGL context and browsers keep
only about 16 alive: a 24-panel page (8 samples x 3) loses its first panels. The file
needs no network when it is opened (plotly.js, ~4.7 MB, is inside it).

Needs plotly (``pip install plotly``, the ``[viewer]`` extra).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pfnet.errors import ConfigError

VIEWER_EXTRA = "pip install plotly (the [viewer] extra of pfnet-completion)"
PANEL_PIXELS = 420
"""Width and height of one panel in the page."""


def _layer_names() -> dict[str, str]:
    """Legend entry of each of the paper's colours."""
    from pfnet.io.palette import GROUND_TRUTH_COLOR, PARTIAL_COLOR, PREDICTION_COLOR

    return {
        PARTIAL_COLOR: "partial input",
        PREDICTION_COLOR: "prediction",
        GROUND_TRUTH_COLOR: "ground truth",
    }


def _bounds(panels: list) -> list[list[float]]:
    """One cube around every point of a row: ``[[lo, hi]] * 3`` per axis (x, z, y drawn)."""
    points = np.concatenate([np.asarray(p, np.float64) for _, layers in panels for p, _ in layers])
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre, half = (lo + hi) / 2.0, max(float((hi - lo).max()) / 2.0, 1e-9) * 1.05
    return [[float(c - half), float(c + half)] for c in centre]


def write_viewer(
    out: str | os.PathLike[str],
    rows: list[tuple[str, list]],
    *,
    title: str | None = None,
    point_size: float = 2.0,
    max_points: int = 50_000,
) -> Path:
    """Write ``rows`` (``(label, [(panel title, [(points, colour), ...]), ...])``) as HTML.

    Args:
        out: Destination ``.html`` file (written atomically; its folder is created).
        rows: As :func:`pfnet.render.render_panels` takes them; already checked there.
        title: Page title, shown above the sample's label.
        point_size: Marker diameter in pixels.
        max_points: Points drawn per cloud and panel (every k-th of a larger cloud).

    Returns:
        The path written.

    Raises:
        MissingDependency: plotly is not installed.
    """
    from pfnet.errors import MissingDependency
    from pfnet.inference.runtimes import has_module
    from pfnet.io.files import atomic_path, output_path
    from pfnet.viz.panels import column_titles as columns_of

    if not has_module("plotly"):
        raise MissingDependency(f"the HTML viewer needs plotly, not installed: {VIEWER_EXTRA}")
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    if Path(out).suffix.lower() != ".html":
        raise ConfigError(f"render: the viewer must be a .html file, got {out}")
    names = _layer_names()
    # One column per panel title (input, completion, ..., ground truth), as in the PNG.
    column_titles = columns_of(rows)
    n_cols = len(column_titles)
    fig = make_subplots(
        rows=1,
        cols=n_cols,
        specs=[[{"type": "scene"}] * n_cols],
        subplot_titles=column_titles,
        horizontal_spacing=0.01,
    )
    owner: list[int] = []  # the row of each trace
    for r, (_label, panels) in enumerate(rows):
        seen: set[str] = set()
        for panel_title, layers in panels:
            k = column_titles.index(panel_title)
            for points, color in layers:
                pts = np.asarray(points, dtype=np.float32)
                if not isinstance(color, str):  # one colour per point (a file's own)
                    codes = np.rint(np.asarray(color, dtype=np.float64) * 255).astype(int)
                    color = [f"rgb({r_},{g},{b})" for r_, g, b in codes]
                if len(pts) > max_points:
                    step = -(-len(pts) // max_points)
                    pts = pts[::step]
                    color = color if isinstance(color, str) else color[::step]
                name = names.get(color, color) if isinstance(color, str) else "its own colours"
                # y-up data: plotly's vertical axis is z, so draw (x, z, y).
                trace = go.Scatter3d(
                    x=pts[:, 0],
                    y=pts[:, 2],
                    z=pts[:, 1],
                    mode="markers",
                    marker={"size": point_size, "color": color},
                    name=name,
                    legendgroup=name,
                    showlegend=name not in seen,
                    visible=r == 0,
                    hoverinfo="skip",
                )
                fig.add_trace(trace, row=1, col=k + 1)
                owner.append(r)
                seen.add(name)
    heading = f"{title}: " if title else ""

    def scenes(r: int) -> dict:
        x, y, z = _bounds(rows[r][1])
        ranges = {"x": x, "y": z, "z": y}  # drawn (x, z, y)
        axis = {"visible": False, "autorange": False}
        scene = {f"{a}axis": {**axis, "range": ranges[a]} for a in "xyz"}
        return {f"scene{k + 1 if k else ''}": scene for k in range(n_cols)}

    def button(r: int, label: str) -> dict:
        layout = {"title.text": heading + label}
        for key, scene in scenes(r).items():
            layout.update({f"{key}.{a}axis.range": scene[f"{a}axis"]["range"] for a in "xyz"})
        return {
            "label": label,
            "method": "update",
            "args": [{"visible": [o == r for o in owner]}, layout],
        }

    buttons = [button(r, label) for r, (label, _) in enumerate(rows)]
    camera = {"up": {"x": 0, "y": 0, "z": 1}, "eye": {"x": 1.3, "y": 1.3, "z": 0.7}}
    fig.update_layout(
        {k: {**v, "aspectmode": "cube", "camera": camera} for k, v in scenes(0).items()}
    )
    fig.update_layout(
        title={"text": heading + rows[0][0], "x": 0.5},
        width=PANEL_PIXELS * n_cols,
        height=PANEL_PIXELS + 140,
        margin={"l": 10, "r": 10, "t": 110, "b": 10},
        paper_bgcolor="white",
        legend={
            "orientation": "h",
            "x": 0.5,
            "xanchor": "center",
            "y": -0.02,
            "itemsizing": "constant",
        },
        updatemenus=[
            {
                "buttons": buttons,
                "x": 0.0,
                "xanchor": "left",
                "y": 1.18,
                "yanchor": "top",
                "showactive": True,
            }
        ]
        if len(rows) > 1
        else [],
    )
    out_path = output_path(out)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out_path) as tmp:
        fig.write_html(
            tmp,
            include_plotlyjs=True,
            full_html=True,
            config={"displaylogo": False, "responsive": False},
        )
    return Path(out)
