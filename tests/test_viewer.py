"""Tests for the interactive HTML viewer (``render --html``, ``--gallery x.html``).

The browser test opens the file in Debian's headless Chromium (software WebGL) and checks
that the points are drawn in the paper's colours; it is skipped where Chromium is absent.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

from pfnet.cli import main
from pfnet.io.clouds import save_npy, write_ply
from pfnet.io.palette import GROUND_TRUTH_COLOR, PARTIAL_COLOR, PREDICTION_COLOR

plotly = pytest.importorskip("plotly")

CHROMIUM = next(
    (shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome") if shutil.which(n)),
    None,
)


@pytest.fixture
def sample_files(tmp_path):
    """A sphere cut in two: partial (x < 0.3) and missing part, and the whole as ground truth."""
    rng = np.random.default_rng(1)
    points = rng.normal(size=(3000, 3))
    sphere = (points / np.linalg.norm(points, axis=1, keepdims=True)).astype(np.float32)
    cut = sphere[:, 0] < 0.3
    write_ply(tmp_path / "partial.ply", sphere[cut])
    save_npy(tmp_path / "pred.npy", sphere[~cut])
    save_npy(tmp_path / "gt.npy", sphere)
    return [str(tmp_path / n) for n in ("partial.ply", "pred.npy", "gt.npy")]


def test_html_is_one_self_contained_file(tmp_path, sample_files, capsys):
    html = tmp_path / "view.html"
    png = tmp_path / "view.png"
    args = ["render", "--sample", *sample_files, "--sample", "-", *sample_files[1:]]
    assert main([*args, "--html", str(html), "--out", str(png), "--title", "spheres"]) == 0
    assert f"wrote {html} (2 row(s))" in capsys.readouterr().out
    assert png.is_file()
    text = html.read_text(encoding="utf-8")
    # plotly.js inside the file, nothing fetched when it is opened
    assert "Plotly" in text and len(text) > 3_000_000
    assert not re.search(r"<script[^>]+src=", text)
    assert not re.search(r"<link[^>]+href=\"?https?:", text)
    for name in ("partial input", "prediction", "ground truth", "spheres: partial"):
        assert name in text
    for colour in (PARTIAL_COLOR, PREDICTION_COLOR, GROUND_TRUTH_COLOR):
        assert colour in text
    assert list(tmp_path.glob(".*")) == []  # no temporary file left


def test_html_errors(tmp_path, sample_files, monkeypatch, capsys):
    assert main(["render", sample_files[0], "--html", str(tmp_path / "x.htm")]) == 1
    assert "--html must be a .html file" in capsys.readouterr().err
    assert main(["render", sample_files[0]]) == 1
    assert "give --out PICTURE.png, --html VIEWER.html or both" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "plotly", None)
    assert main(["render", sample_files[0], "--html", str(tmp_path / "x.html")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "pip install plotly" in err
    assert not (tmp_path / "x.html").exists()


def test_evaluate_gallery_as_html(tmp_path, tiny_dataset):
    from pfnet.data import load_split, test_protocol_crop

    clouds = load_split(tiny_dataset, "test")
    _, removed = test_protocol_crop(np.asarray(clouds.points), 0.25)
    pred = tmp_path / "pred"
    for cat, name, points in zip(clouds.category, clouds.name, removed, strict=True):
        (pred / str(cat)).mkdir(parents=True, exist_ok=True)
        save_npy(pred / str(cat) / f"{name}.npy", points)
    html = tmp_path / "g.html"
    args = ["evaluate", str(pred), "--data", str(tiny_dataset), "--gallery", str(html)]
    assert main([*args, "--gallery-count", "3"]) == 0
    text = html.read_text(encoding="utf-8")
    assert text.count('"method":"update"') == 3  # one menu entry per sample
    assert "ground truth" in text and "completion" in text


def _colour_pixels(image: np.ndarray, hex_colour: str, tol: float = 0.1) -> int:
    rgb = np.array([int(hex_colour[i : i + 2], 16) / 255 for i in (1, 3, 5)])
    return int((np.abs(image - rgb).max(axis=-1) < tol).sum())


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="needs Chromium (apt-get install chromium)")
def test_viewer_draws_points_in_headless_chromium(tmp_path, sample_files):
    import matplotlib.image

    html = tmp_path / "view.html"
    assert main(["render", "--sample", *sample_files, "--html", str(html)]) == 0
    shot = tmp_path / "shot.png"
    subprocess.run(
        [
            CHROMIUM,
            "--headless",
            "--no-sandbox",  # CI runs as root
            "--enable-unsafe-swiftshader",  # software WebGL: no GPU needed
            "--use-angle=swiftshader",
            "--hide-scrollbars",
            "--window-size=1300,600",
            "--virtual-time-budget=15000",
            f"--screenshot={shot}",
            html.as_uri(),
        ],
        capture_output=True,
        timeout=180,
        check=True,
    )
    image = matplotlib.image.imread(shot)[..., :3]
    plot_area = image[130:520]  # below the titles, above the legend
    counts = {
        colour: _colour_pixels(plot_area, colour)
        for colour in (PARTIAL_COLOR, PREDICTION_COLOR, GROUND_TRUTH_COLOR)
    }
    assert all(count > 300 for count in counts.values()), counts
    # the three panels side by side: blue only in the right third, yellow in the middle one
    third = plot_area.shape[1] // 3
    assert _colour_pixels(plot_area[:, 2 * third :], GROUND_TRUTH_COLOR) > 300
    assert _colour_pixels(plot_area[:, :third], PREDICTION_COLOR) == 0
