"""Tests for ``pfnet complete``: input points kept bit-exact, any size, bad files, mapping back."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from pfnet.cli import main  # noqa: E402
from pfnet.errors import DataError  # noqa: E402
from pfnet.inference.checkpoint import save_checkpoint  # noqa: E402
from pfnet.inference.completion import complete_clouds, output_paths  # noqa: E402
from pfnet.inference.predict import network_input, normalisation  # noqa: E402
from pfnet.io.clouds import read_point_cloud, save_npy, write_ply  # noqa: E402
from pfnet.models import build_model  # noqa: E402
from pfnet.training.config import preset_config  # noqa: E402

N_POINTS = 512  # the model's complete cloud: it takes 384 points and predicts 128


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    config = preset_config("small").replace(n_points=N_POINTS)
    torch.manual_seed(0)
    model = build_model(config).eval()
    path = tmp_path_factory.mktemp("ckpt") / "model.pt"
    save_checkpoint(path, {"config": config.to_dict(), "model": model.state_dict()})
    return path, model


def _scan(n: int, seed: int) -> np.ndarray:
    """A half-sphere 'scan' in arbitrary units and position, float32."""
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(n, 3))
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    points[:, 0] = np.abs(points[:, 0])
    return (points * 37.5 + [100.0, -20.0, 3.0]).astype(np.float32)


def _write(path, points):
    if path.suffix == ".ply":
        write_ply(path, points)
    elif path.suffix == ".npy":
        save_npy(path, points)
    elif path.suffix == ".pcd":
        head = (
            "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
            f"WIDTH {len(points)}\nHEIGHT 1\nPOINTS {len(points)}\nDATA binary\n"
        )
        path.write_bytes(head.encode() + points.astype("<f4").tobytes())
    else:
        sep = "," if path.suffix == ".txt" else " "
        path.write_text("\n".join(sep.join(repr(float(v)) for v in p) for p in points))


def test_complete_keeps_input_points_bit_exact(tmp_path, checkpoint, capsys):
    path, _ = checkpoint
    inputs = []
    for k, (suffix, n) in enumerate(
        [(".ply", 1000), (".npy", 384), (".xyz", 100), (".pts", 5), (".txt", 700), (".pcd", 2000)]
    ):
        file = tmp_path / f"scan{k}{suffix}"
        _write(file, _scan(n, k))
        inputs.append(file)
    out = tmp_path / "out"
    args = ["complete", *map(str, inputs), "--checkpoint", str(path), "--out", str(out)]
    assert main([*args, "--batch-size", "4", "--device", "cpu"]) == 0
    assert "completed 6 of 6 file(s)" in capsys.readouterr().out
    for file in inputs:
        cloud = read_point_cloud(file)
        missing_path, completed_path = output_paths(out, file)
        missing = read_point_cloud(missing_path)
        completed = read_point_cloud(completed_path)
        assert missing.shape == (N_POINTS // 4, 3)
        assert completed.shape == (len(cloud) + len(missing), 3)
        # Every input point, in order, with the same bits; then the prediction.
        assert completed[: len(cloud)].tobytes() == cloud.tobytes()
        assert completed[len(cloud) :].tobytes() == missing.tobytes()
        # The prediction is mapped back near the input (radius 37.5 around (100, -20, 3)).
        assert np.abs(missing.mean(axis=0) - [100.0, -20.0, 3.0]).max() < 2 * 37.5


def test_prediction_follows_the_input_frame(checkpoint):
    _, model = checkpoint
    cloud = _scan(600, 7)
    moved = (cloud.astype(np.float64) * 0.01 - [5.0, 6.0, 7.0]).astype(np.float32)
    a, b = complete_clouds(model, [cloud, moved], batch_size=2)
    # Normalisation removes translation and scale, so predictions map back equivariantly.
    np.testing.assert_allclose(b, a.astype(np.float64) * 0.01 - [5.0, 6.0, 7.0], atol=1e-4)


def test_network_input_resampling_rule():
    rng = np.random.default_rng(0)
    cloud = rng.normal(size=(50, 3)).astype(np.float32)
    small = network_input(cloud, 120)
    np.testing.assert_array_equal(small, cloud[np.arange(120) % 50])
    big = network_input(cloud, 20)
    assert big.shape == (20, 3)
    np.testing.assert_array_equal(big[0], cloud[0])  # IFPS starts at the first point
    rows = {r.tobytes() for r in cloud}
    assert all(r.tobytes() in rows for r in big) and len({r.tobytes() for r in big}) == 20
    np.testing.assert_array_equal(network_input(cloud, 50), cloud)


def test_normalisation_matches_data_preparation():
    from pfnet.data.sampling import normalize

    cloud = _scan(300, 2)
    t = normalisation(cloud)
    np.testing.assert_allclose(t.apply(cloud), normalize(cloud), atol=1e-6)
    np.testing.assert_allclose(t.invert(t.apply(cloud)), cloud, atol=1e-4)
    with pytest.raises(DataError, match=r"x\.ply: all 4 points coincide"):
        normalisation(np.ones((4, 3)), "x.ply")


def test_bad_files_are_reported_and_the_rest_processed(tmp_path, checkpoint, capsys):
    path, _ = checkpoint
    good = tmp_path / "good.npy"
    save_npy(good, _scan(400, 1))
    nan = tmp_path / "nan.xyz"
    nan.write_text("1 2 3\nnan 1 1\n")
    flat = tmp_path / "flat.npy"
    save_npy(flat, np.ones((10, 3)))
    out = tmp_path / "out"
    inputs = [str(tmp_path / "absent.ply"), str(nan), str(good), str(flat)]
    code = main(["complete", *inputs, "--checkpoint", str(path), "--out", str(out)])
    captured = capsys.readouterr()
    assert code == 2
    assert "completed 1 of 4 file(s)" in captured.out
    assert "absent.ply: no such file" in captured.err
    assert "nan.xyz: 1 point(s) have NaN" in captured.err
    assert "flat.npy: all 10 points coincide" in captured.err
    assert sorted(p.name for p in out.iterdir()) == ["good_completed.ply", "good_missing.ply"]


def test_complete_errors(tmp_path, checkpoint, capsys):
    path, _ = checkpoint
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    for folder in ("a", "b"):
        save_npy(tmp_path / folder / "scan.npy", _scan(50, 0))
    a, b = str(tmp_path / "a" / "scan.npy"), str(tmp_path / "b" / "scan.npy")
    out = str(tmp_path / "out")
    assert main(["complete", a, b, "--checkpoint", str(path), "--out", out]) == 1
    assert "would both write scan_completed.ply" in capsys.readouterr().err
    assert main(["complete", a, "--checkpoint", str(tmp_path / "x.pt"), "--out", out]) == 1
    assert "x.pt does not exist" in capsys.readouterr().err
    assert main(["complete", a, "--checkpoint", str(path), "--out", out, "--batch-size", "0"]) == 1
    assert "--batch-size must be at least 1" in capsys.readouterr().err
    # The same file twice is completed once.
    assert main(["complete", a, a, "--checkpoint", str(path), "--out", out]) == 0
    assert "completed 1 of 1 file(s)" in capsys.readouterr().out


class _Guess(torch.nn.Module):
    """A stand-in network: the same predicted points whatever the input."""

    def __init__(self, detail: np.ndarray, n_points: int) -> None:
        super().__init__()
        self.detail = torch.from_numpy(detail.astype(np.float32))
        self.n_points, self.n_missing = n_points, len(detail)

    def forward(self, partial):
        from types import SimpleNamespace

        return SimpleNamespace(detail=self.detail.expand(len(partial), -1, -1))


def test_the_mirror_fill_puts_the_points_near_the_scans_mirror_image_on_its_surface():
    from pfnet.data.symmetry import mirror_fill
    from pfnet.geometry import nearest_neighbors
    from pfnet.inference.predict import input_frame

    rng = np.random.default_rng(3)  # a box's surface, symmetric about x = 0; a corner missing
    half = np.array([1.0, 0.5, 0.3])
    box = rng.uniform(-1.0, 1.0, (4000, 3)) * half
    face = rng.integers(3, size=len(box))  # each point pushed onto one of its two faces
    rows = np.arange(len(box))
    box[rows, face] = np.sign(box[rows, face]) * half[face]
    hole = (box[:, 0] > 0.55) & (box[:, 2] < 0.0)
    scan = (box[~hole] * 37.0 + [5.0, -3.0, 2.0]).astype(np.float32)
    missing = (box[hole] * 37.0 + [5.0, -3.0, 2.0]).astype(np.float32)
    frame = input_frame(scan.astype(np.float64), "scan")
    near = frame.apply(missing[rng.choice(len(missing), 128)].astype(np.float64))  # a network's
    blob = near + rng.normal(0, 0.05, (128, 3))  # noisy guess of the missing corner
    guess = _Guess(blob, n_points=len(scan) + 400)  # the scan is smaller than the input

    (plain,) = complete_clouds(guess, [scan], mirror_fill=0.0)
    np.testing.assert_allclose(plain, frame.invert(blob.astype(np.float32)), atol=1e-3)
    (filled,) = complete_clouds(guess, [scan], mirror_fill=0.15)
    expected = mirror_fill(blob, frame.apply(scan.astype(np.float64)), reach=0.15)
    np.testing.assert_allclose(filled, frame.invert(expected), atol=1e-3)

    def on_surface(points):  # within about the sample's spacing (0.02) of the missing corner
        sq_dist, _ = nearest_neighbors(np.ascontiguousarray(points, np.float32), missing)
        return float((np.sqrt(sq_dist) < 0.03 * frame.radius).mean())

    assert on_surface(filled) > 0.8 > 0.5 > on_surface(plain)  # measured: 0.90 and 0.38


def test_complete_fills_from_the_mirror_by_default_and_says_so(tmp_path, checkpoint, capsys):
    from pfnet.inference.completion import DEFAULT_MIRROR_FILL

    path, model = checkpoint
    scan = _scan(600, 4)
    save_npy(tmp_path / "scan.npy", scan)
    (plain,) = complete_clouds(model, [scan], mirror_fill=0.0)
    (filled,) = complete_clouds(model, [scan], mirror_fill=DEFAULT_MIRROR_FILL)
    for extra, expected, said in (
        ([], filled, f"mirror fill within {DEFAULT_MIRROR_FILL:g}"),
        (["--mirror-fill", "0"], plain, "the network's points only (--mirror-fill 0)"),
    ):
        out = tmp_path / f"out{len(extra)}"
        command = ["complete", str(tmp_path / "scan.npy"), "--checkpoint", str(path)]
        assert main([*command, "--out", str(out), *extra]) == 0
        assert said in capsys.readouterr().out
        np.testing.assert_allclose(read_point_cloud(out / "scan_missing.ply"), expected, atol=1e-5)
    bad = ["complete", str(tmp_path / "scan.npy"), "--out", str(tmp_path / "x"), "--mirror-fill"]
    assert main([*bad, "-1"]) == 1
    assert "--mirror-fill must be a distance >= 0 (0: off), got -1.0" in capsys.readouterr().err
