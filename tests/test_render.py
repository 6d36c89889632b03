"""Tests for pfnet.viz.rendering: galleries and the ``pfnet render`` command."""

from __future__ import annotations

import numpy as np
import pytest

from pfnet.cli import main
from pfnet.errors import ConfigError, DataError
from pfnet.io.clouds import save_npy, write_ply
from pfnet.io.palette import GROUND_TRUTH_COLOR, PARTIAL_COLOR, PREDICTION_COLOR
from pfnet.viz.rendering import RenderSample, render_gallery, row_label

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _png_size(path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


def _pixels(path) -> np.ndarray:
    import matplotlib.image

    return matplotlib.image.imread(path)[..., :3]


def _has_colour(image: np.ndarray, hex_colour: str, tol: float = 0.12) -> bool:
    rgb = np.array([int(hex_colour[i : i + 2], 16) / 255 for i in (1, 3, 5)])
    return bool((np.abs(image - rgb).max(axis=-1) < tol).any())


@pytest.fixture
def sphere() -> np.ndarray:
    rng = np.random.default_rng(1)
    points = rng.normal(size=(400, 3))
    return (points / np.linalg.norm(points, axis=1, keepdims=True)).astype(np.float32)


def test_gallery_rows_panels_and_colours(tmp_path, sphere):
    partial, missing = sphere[sphere[:, 0] < 0.5], sphere[sphere[:, 0] >= 0.5]
    samples = [
        RenderSample("a/full", partial, missing, sphere),
        RenderSample("b/only-gt", ground_truth=sphere),
    ]
    out = render_gallery(
        tmp_path / "sub" / "g.png", samples, views=2, dpi=50, panel_inches=2, point_size=40
    )
    assert out == tmp_path / "sub" / "g.png"
    width, height = _png_size(out)
    # 3 panels x 2 views per row, 2 rows.
    assert width > 2.5 * height
    image = _pixels(out)
    for colour in (PARTIAL_COLOR, PREDICTION_COLOR, GROUND_TRUTH_COLOR):
        assert _has_colour(image, colour), colour
    assert [p.name for p in out.parent.iterdir()] == ["g.png"]


def test_gallery_prediction_only_is_yellow_not_blue(tmp_path, sphere):
    out = render_gallery(
        tmp_path / "p.png", [RenderSample("x", prediction=sphere)], views=1, point_size=40
    )
    image = _pixels(out)
    assert _has_colour(image, PREDICTION_COLOR)
    assert not _has_colour(image, GROUND_TRUTH_COLOR)


def test_gallery_errors(tmp_path, sphere):
    with pytest.raises(ConfigError, match="no samples"):
        render_gallery(tmp_path / "g.png", [])
    with pytest.raises(ConfigError, match="'empty' has no point cloud"):
        render_gallery(tmp_path / "g.png", [RenderSample("empty")])
    with pytest.raises(ConfigError, match=r"views must be in \[1, 12\]"):
        render_gallery(tmp_path / "g.png", [RenderSample("s", sphere)], views=0)
    bad = sphere.copy()
    bad[0, 0] = np.nan
    with pytest.raises(DataError, match=r"'s' has a cloud of shape \(400, 3\) that is not"):
        render_gallery(tmp_path / "g.png", [RenderSample("s", prediction=bad)])
    with pytest.raises(DataError, match=r"shape \(400, 2\)"):
        render_gallery(tmp_path / "g.png", [RenderSample("s", sphere[:, :2])])
    assert list(tmp_path.iterdir()) == []


def test_render_command_files_and_samples(tmp_path, sphere, capsys):
    write_ply(tmp_path / "gt.ply", sphere)
    save_npy(tmp_path / "partial.npy", sphere[sphere[:, 1] < 0])
    np.savetxt(tmp_path / "pred.xyz", sphere[sphere[:, 1] >= 0])
    out = tmp_path / "r.png"
    code = main(
        [
            "render",
            str(tmp_path / "gt.ply"),
            "--sample",
            str(tmp_path / "partial.npy"),
            str(tmp_path / "pred.xyz"),
            str(tmp_path / "gt.ply"),
            "--sample",
            str(tmp_path / "partial.npy"),
            "-",
            "-",
            "--out",
            str(out),
            "--views",
            "1",
            "--title",
            "spheres",
        ]
    )
    assert code == 0
    assert f"wrote {out} (3 row(s))" in capsys.readouterr().out
    width, height = _png_size(out)
    assert height > width / 3


def test_render_command_errors(tmp_path, sphere, capsys):
    assert main(["render", "--out", str(tmp_path / "x.png")]) == 1
    assert "give at least one FILE" in capsys.readouterr().err
    write_ply(tmp_path / "a.ply", sphere)
    assert main(["render", str(tmp_path / "a.ply"), "--out", str(tmp_path / "x.jpg")]) == 1
    assert "--out must be a .png file" in capsys.readouterr().err
    assert main(["render", "--sample", "-", "-", "-", "--out", str(tmp_path / "x.png")]) == 1
    assert "at least one file that is not '-'" in capsys.readouterr().err
    (tmp_path / "bad.xyz").write_text("1 2\n")
    assert main(["render", str(tmp_path / "bad.xyz"), "--out", str(tmp_path / "x.png")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("pfnet render: error: ") and "bad.xyz: line 1 has 2 column" in err
    assert not (tmp_path / "x.png").exists()


def test_render_panels_draws_any_columns(tmp_path, sphere):
    from pfnet.viz.rendering import render_panels

    rows = [
        ("chair/a_long_name_0001", [("input", [(sphere, PARTIAL_COLOR)])]
         + [(f"model {k}", [(sphere, PARTIAL_COLOR), (sphere + 2.0, PREDICTION_COLOR)])
            for k in range(4)]
         + [("ground truth", [(sphere, GROUND_TRUTH_COLOR)])]),
        ("lamp/b", [("input", [(sphere, PARTIAL_COLOR)])]),
    ]  # fmt: skip
    out = render_panels(tmp_path / "grid.png", rows, title="six columns", dpi=40, point_size=9)
    width, height = _png_size(out)
    assert (width, height) == (round((2.2 * 6 + 0.6) * 40), round((2.2 * 2 + 0.4) * 40))
    image = _pixels(out)
    for colour in (PARTIAL_COLOR, PREDICTION_COLOR, GROUND_TRUTH_COLOR):
        assert _has_colour(image, colour)
    with pytest.raises(ConfigError, match="sample 'x' has no point cloud"):
        render_panels(tmp_path / "e.png", [("x", [])])
    with pytest.raises(DataError, match="sample 'y' has a cloud of shape"):
        render_panels(tmp_path / "e.png", [("y", [("input", [(sphere[:, :2], PARTIAL_COLOR)])])])


def test_row_label_fits_beside_its_row():
    assert row_label("cabinet/blend_swap_cc-0_uppercornercabinet", 1.7, 8) == (
        "cabinet/\nblend_swap_cc-\n0_uppercornercabinet"
    )
    long = "chair/" + "x" * 60
    lines = row_label(long, 1.7, 8).split("\n")
    assert lines[0] == "chair/" and all(len(line) <= 25 for line in lines)
    assert "".join(lines) == long
    assert row_label("scan.ply", 1.7, 8) == "scan.ply"


def _cells(image: np.ndarray, rows: int, cols: int, panel: float = 2.2) -> dict:
    """The pixels of each (row, column) panel of a gallery drawn with one view and no title
    (0.5 inch of row labels on the left, 0.4 inch of column titles above)."""
    height, width = image.shape[:2]
    inch_x, inch_y = width / (panel * cols + 0.6), height / (panel * rows + 0.4)
    cells = {}
    for r in range(rows):
        for c in range(cols):
            x0, y0 = int((0.5 + c * panel * 1.0) * inch_x), int((0.4 + r * panel) * inch_y)
            cells[r, c] = image[y0 : y0 + int(panel * inch_y), x0 : x0 + int(panel * inch_x)]
    return cells


def test_render_draws_a_completed_file_in_its_own_colours_not_as_ground_truth(tmp_path, sphere):
    """`pfnet render x_completed.ply` (grey scan, yellow prediction, as `pfnet complete` writes
    it) draws those colours under "completion", not everything blue under "ground truth"."""
    from pfnet.inference.completion import write_completion
    from pfnet.viz.rendering import own_color_panel

    scan, missing = sphere[sphere[:, 0] < 0.5], sphere[sphere[:, 0] >= 0.5]
    write_completion(tmp_path, tmp_path / "x.xyz", scan, missing)
    completed = tmp_path / "x_completed.ply"
    out = tmp_path / "r.png"
    argv = ["render", str(completed), "--out", str(out), "--views", "1", "--point-size", "40"]
    assert main(argv) == 0
    image = _pixels(out)
    assert _has_colour(image, PARTIAL_COLOR) and _has_colour(image, PREDICTION_COLOR)
    assert not _has_colour(image, GROUND_TRUTH_COLOR)
    from pfnet.io.formats.ply import read_ply_colors

    title, layers = own_color_panel(*(f(completed) for f in (_read, read_ply_colors)))
    assert title == "completion" and [len(p) for p, _ in layers] == [len(scan), len(missing)]
    assert own_color_panel(missing, np.tile([0.2, 0.4, 0.6], (len(missing), 1)))[0] == (
        "its own colours"
    )
    # --role still decides for every file; a file without colours is the ground truth
    grey = _count(image, PARTIAL_COLOR)
    assert main([*argv, "--role", "prediction"]) == 0
    assert _count(_pixels(out), PARTIAL_COLOR) < grey / 10  # the label's anti-aliased text
    write_ply(tmp_path / "plain.ply", sphere)
    assert main(["render", str(tmp_path / "plain.ply"), *argv[2:]]) == 0
    assert _has_colour(_pixels(out), GROUND_TRUTH_COLOR)


def _count(image: np.ndarray, hex_colour: str, tol: float = 0.12) -> int:
    rgb = np.array([int(hex_colour[i : i + 2], 16) / 255 for i in (1, 3, 5)])
    return int((np.abs(image - rgb).max(axis=-1) < tol).sum())


def _read(path):
    from pfnet.io.clouds import read_point_cloud

    return read_point_cloud(path)


def test_render_samples_with_a_dash_keep_every_panel_under_its_header(tmp_path, sphere):
    """A row without a prediction ('-') leaves the completion's cell empty: its ground truth
    stays in the ground-truth column, under that header, as in a full row."""
    from pfnet.viz.panels import column_titles

    partial, missing = sphere[sphere[:, 0] < 0.5], sphere[sphere[:, 0] >= 0.5]
    save_npy(tmp_path / "p.npy", partial)
    save_npy(tmp_path / "m.npy", missing)
    save_npy(tmp_path / "g.npy", sphere)
    out = tmp_path / "r.png"
    files = [str(tmp_path / n) for n in ("p.npy", "m.npy", "g.npy")]
    argv = ["render", "--sample", files[0], "-", files[2], "--sample", *files]
    assert main([*argv, "--out", str(out), "--views", "1", "--point-size", "40"]) == 0
    cells = _cells(_pixels(out), rows=2, cols=3)
    assert not _has_colour(cells[0, 1], GROUND_TRUTH_COLOR)  # under "completion": nothing
    assert _has_colour(cells[0, 2], GROUND_TRUTH_COLOR)  # under "ground truth"
    assert _has_colour(cells[1, 1], PREDICTION_COLOR) and _has_colour(
        cells[1, 2], GROUND_TRUTH_COLOR
    )
    b = [("prediction", []), ("ground truth", []), ("x", [])]
    rows = [("a", [("input", []), ("ground truth", [])]), ("b", b)]
    assert column_titles(rows) == ["input", "prediction", "ground truth", "x"]
