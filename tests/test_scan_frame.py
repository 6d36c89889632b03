"""The scan protocol: the scan frame, its poses, the training data in it, the mirror baseline,
and ``pfnet.complete`` / ``pfnet complete --up`` (DESIGN.md §3)."""

from __future__ import annotations

import numpy as np
import pytest

from pfnet.data.scan_frame import scan_angle, scan_normalisation, scan_pose, to_y_up, up_rotation
from pfnet.data.symmetry import estimate_mirror_plane, mirror_completion, mirror_fill, reflect
from pfnet.errors import ConfigError, DataError
from pfnet.models.config import ModelConfig


def test_z_up_turns_to_y_up_by_a_proper_rotation():
    turn = to_y_up("z")
    np.testing.assert_array_equal(turn @ [0.0, 0.0, 1.0], [0.0, 1.0, 0.0])
    assert np.linalg.det(turn) == pytest.approx(1.0)
    np.testing.assert_array_equal(to_y_up("y"), np.eye(3))
    with pytest.raises(ConfigError, match=r"up axis must be one of y, z, got 'x'"):
        to_y_up("x")


def test_up_rotation_keeps_the_up_coordinate_and_matches_the_augmentation():
    from pfnet.data.augment import Augmentation

    points = np.random.default_rng(0).normal(size=(20, 3))
    turned = points @ up_rotation(0.7, 1).T
    np.testing.assert_allclose(turned[:, 1], points[:, 1])
    np.testing.assert_allclose(np.linalg.norm(turned, axis=1), np.linalg.norm(points, axis=1))

    class Fixed:
        def uniform(self, low, high, size=None):
            return 0.7

    augmented = Augmentation(up_axis=1)(points, Fixed())
    np.testing.assert_allclose(augmented, turned, atol=1e-5)


@pytest.mark.parametrize("up", ["y", "z"])
def test_scan_poses_are_deterministic_similarities_that_invert(up):
    points = np.random.default_rng(1).normal(size=(30, 3))
    pose = scan_pose(3, up=up)
    again = scan_pose(3, up=up)
    np.testing.assert_array_equal(pose.rotation, again.rotation)
    assert pose.scale == again.scale and 0.1 <= pose.scale <= 10
    np.testing.assert_allclose(pose.invert(pose.apply(points)), points, atol=1e-9)
    assert np.linalg.det(pose.rotation) == pytest.approx(1.0)
    # distances scale by the pose's factor only
    moved = pose.apply(points)
    np.testing.assert_allclose(
        np.linalg.norm(moved[1:] - moved[0], axis=1),
        pose.scale * np.linalg.norm(points[1:] - points[0], axis=1),
    )
    # y-up: the y coordinate only scaled and shifted; z-up: the data set's y lands on z
    axis = 1 if up == "y" else 2
    np.testing.assert_allclose(moved[:, axis], pose.scale * points[:, 1] + pose.shift[axis])
    assert scan_pose(4, up=up).scale != pose.scale
    unturned = scan_pose(3, up=up, turn=False)
    assert unturned.scale == pose.scale  # the same scale and offset, only no turn
    np.testing.assert_allclose(unturned.rotation, to_y_up(up).T, atol=1e-12)


def test_scan_normalisation_is_the_partials_own_frame():
    cloud = np.random.default_rng(2).normal(size=(100, 3)) * 5 + 40
    frame = scan_normalisation(cloud)
    normalised = frame.apply(cloud)
    np.testing.assert_allclose(normalised.mean(axis=0), 0, atol=1e-5)
    assert np.linalg.norm(normalised, axis=1).max() == pytest.approx(1.0, abs=1e-6)
    identity = scan_normalisation(np.ones((3, 3)))
    assert identity.radius == 1.0


def test_frame_is_a_model_setting_with_a_clear_error():
    assert ModelConfig().frame == "shape"  # model files without the key: the paper's frame
    assert ModelConfig(frame="scan").frame == "scan"
    with pytest.raises(
        ConfigError,
        match=r"frame must be one of shape, scan, aligned, heading, aligned-end, aligned-rim, "
        r"rim; got 'world'",
    ):
        ModelConfig(frame="world")


def _symmetric_cloud(n=3000, seed=0):
    """A box-and-legs 'table' symmetric about the plane x = 0.1, y up, unit scale."""
    rng = np.random.default_rng(seed)
    top = np.column_stack([rng.uniform(-0.8, 0.8, n), np.full(n, 0.5), rng.uniform(-0.4, 0.4, n)])
    legs = []
    for x, z in [(-0.7, -0.3), (0.7, -0.3), (-0.7, 0.3), (0.7, 0.3)]:
        m = n // 8
        legs.append(np.column_stack([np.full(m, x), rng.uniform(-0.5, 0.5, m), np.full(m, z)]))
    cloud = np.concatenate([top, *legs])
    cloud[:, 0] += 0.1
    return cloud


def test_mirror_plane_and_completion_fill_a_missing_side():
    cloud = _symmetric_cloud()
    hole = (cloud[:, 0] > 0.55) & (cloud[:, 2] < 0.1)  # one corner of the table, a leg too
    partial, missing = cloud[~hole], cloud[hole]
    planes = estimate_mirror_plane(partial, up_axis=1)
    normals = [abs(p.normal[0]) for p in planes]
    assert max(normals) == pytest.approx(1.0, abs=0.01)  # the x-plane is among them
    x_plane = planes[int(np.argmax(normals))]
    assert abs(x_plane.offset * np.sign(x_plane.normal[0]) - 0.1) < 0.03
    np.testing.assert_allclose(
        reflect(reflect(partial, x_plane.normal, 0.3), x_plane.normal, 0.3), partial, atol=1e-12
    )
    filled = mirror_completion(partial, 200, up_axis=1)
    assert filled.shape == (200, 3) and filled.dtype == np.float32
    from pfnet.geometry import nearest_neighbors

    to_missing, _ = nearest_neighbors(filled, missing.astype(np.float32))
    assert np.median(np.sqrt(to_missing)) < 0.05  # most mirrored points lie in the hole
    with pytest.raises(DataError, match="a mirror plane needs an"):
        estimate_mirror_plane(np.zeros((1, 3)))


def test_the_coarse_plane_search_finds_the_exhaustive_searchs_planes(monkeypatch):
    import pfnet.data.symmetry as symmetry

    rng = np.random.default_rng(5)
    clouds = []
    for _ in range(6):  # noisy boxes' surfaces, nearly square from above, a random piece cut
        half = np.array([1.0, rng.uniform(0.3, 0.8), rng.uniform(0.7, 0.95)])
        box = rng.uniform(-1.0, 1.0, (2400, 3)) * half
        face = rng.integers(3, size=len(box))
        box[np.arange(len(box)), face] = np.sign(box[np.arange(len(box)), face]) * half[face]
        box += rng.normal(0.0, 0.01, box.shape)
        towards = rng.normal(size=3)
        cut = box @ (towards / np.linalg.norm(towards)) > rng.uniform(0.2, 0.5)
        clouds.append(box[~cut] / np.linalg.norm(box[~cut], axis=1).max())
    assert all(len(c) > 2 * symmetry.SEARCH_POINTS for c in clouds)
    found = [estimate_mirror_plane(c) for c in clouds]
    monkeypatch.setattr(symmetry, "SEARCH_POINTS", 10**9)  # every plane on every point
    for cloud, planes in zip(clouds, found, strict=True):
        exhaustive = estimate_mirror_plane(cloud)
        assert len(planes) == len(exhaustive)
        for got, want in zip(planes, exhaustive, strict=True):
            np.testing.assert_array_equal(got.normal, want.normal)
            assert got.offset == want.offset and got.inliers == want.inliers


def test_mirror_fill_puts_the_images_the_prediction_agrees_with_on_the_surface():
    from pfnet.geometry import nearest_neighbors

    cloud = _symmetric_cloud()
    hole = (cloud[:, 0] > 0.55) & (cloud[:, 2] < 0.1)
    partial, missing = cloud[~hole], cloud[hole].astype(np.float32)
    rng = np.random.default_rng(1)
    blob = missing.mean(axis=0) + rng.normal(0.0, 0.05, (150, 3))  # a network's compact guess
    stray = np.array([0.0, -2.0, 0.0]) + rng.normal(0.0, 0.01, (50, 3))  # far from any image
    predicted = np.concatenate([blob, stray]).astype(np.float32)

    def on_surface(points):  # share of the points within 0.02 of the missing piece
        sq_dist, _ = nearest_neighbors(np.ascontiguousarray(points, np.float32), missing)
        return float((sq_dist < 0.02**2).mean())

    filled = mirror_fill(predicted, partial)  # reach 0.15
    assert filled.shape == predicted.shape and filled.dtype == np.float32
    assert on_surface(filled) > 0.5 > 0.1 > on_surface(predicted)
    kept = {tuple(p) for p in stray.astype(np.float32)}  # no image near them: they stay
    assert sum(tuple(p) in kept for p in filled) == len(stray)
    np.testing.assert_array_equal(mirror_fill(predicted, partial, reach=0.0), predicted)
    nowhere = np.full((20, 3), 5.0, np.float32)  # no image within reach: the prediction stays
    np.testing.assert_array_equal(mirror_fill(nowhere, partial, reach=0.15), nowhere)


def test_a_bare_folder_named_like_a_runtime_is_not_that_runtime(tmp_path, monkeypatch):
    """An output folder `torch/` in the working directory made the light install take it for
    PyTorch (and fail on torch.cuda)."""
    from pfnet.inference.runtimes import has_module

    (tmp_path / "pfnet_runtime_stand_in").mkdir()
    monkeypatch.syspath_prepend(str(tmp_path))
    assert not has_module("pfnet_runtime_stand_in")
    assert has_module("numpy")


torch = pytest.importorskip("torch")


@pytest.fixture(scope="module")
def scan_model(tmp_path_factory):
    from pfnet.inference.checkpoint import save_checkpoint
    from pfnet.models import build_model
    from pfnet.training.config import preset_config

    config = preset_config("small").replace(n_points=512)
    assert config.frame == "scan"  # the small preset trains for what `complete` gives
    torch.manual_seed(0)
    model = build_model(config).eval()
    path = tmp_path_factory.mktemp("scan-model") / "model.pt"
    save_checkpoint(path, {"config": config.to_dict(), "model": model.state_dict()})
    return path


def _scan(n=400, seed=5):
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(n, 3)) * [1.0, 2.0, 0.5]
    points[:, 0] = np.abs(points[:, 0])
    return points


def test_complete_keeps_a_float64_survey_scan_exact_and_precise(scan_model):
    import pfnet

    # UTM-like coordinates: a 4 m object half a million metres from the origin
    scan = _scan() + [512_345.0, 5_412_345.0, 230.0]
    result = pfnet.complete(scan, str(scan_model), runtime="torch", device="cpu")
    assert result.completed.dtype == np.float64
    assert result.completed[: len(scan)].tobytes() == scan.tobytes()
    assert result.missing.shape == (128, 3)
    assert result.frame == "scan" and result.runtime == "torch"
    near = (_scan() + [0.0, 0.0, 0.0]).astype(np.float64)
    at_origin = pfnet.complete(near, str(scan_model), runtime="torch", device="cpu")
    # translation is removed in float64: the two predictions differ by the offset alone
    np.testing.assert_allclose(
        result.missing - [512_345.0, 5_412_345.0, 230.0], at_origin.missing, atol=1e-4
    )
    assert "missing=128 points" in repr(result)


def test_complete_up_z_is_the_y_up_completion_stood_up(scan_model):
    import pfnet

    scan = _scan()
    turn = to_y_up("z")  # y-up to z-up is its transpose
    y_up = pfnet.complete(scan, str(scan_model), runtime="torch", device="cpu")
    z_up = pfnet.complete(scan @ turn, str(scan_model), up="z", runtime="torch", device="cpu")
    np.testing.assert_allclose(z_up.missing, y_up.missing @ turn, atol=1e-4)


@pytest.mark.parametrize(
    ("points", "message"),
    [
        (np.zeros((5, 2)), r"points must have shape \(N, 3\) with N >= 1, got \(5, 2\)"),
        (np.array([[0.0, np.nan, 1.0]] * 4), "points holds NaN or infinite coordinates"),
        (np.array([["a", "b", "c"]]), "points must hold numbers, got dtype <U1"),
        (np.ones((4, 3)), "all 4 points coincide"),
    ],
)
def test_complete_refuses_bad_points_clearly(scan_model, points, message):
    import pfnet

    with pytest.raises(DataError, match=message):
        pfnet.complete(points, str(scan_model), runtime="torch", device="cpu")


def test_complete_refuses_an_unknown_up_axis_before_loading():
    import pfnet

    with pytest.raises(ConfigError, match="up axis must be one of y, z"):
        pfnet.complete(_scan(), "no-such-model", up="x")
    for reach in (-0.1, float("nan"), "0.1"):
        with pytest.raises(ConfigError, match="mirror fill must be a finite distance >= 0"):
            pfnet.complete(_scan(), "no-such-model", mirror_fill=reach)


def test_complete_command_up_z_says_model_frame_and_files(scan_model, tmp_path, capsys):
    from pfnet.cli import main
    from pfnet.io.clouds import read_point_cloud, save_npy

    scan = (_scan() @ to_y_up("z")).astype(np.float32)
    save_npy(tmp_path / "scan.npy", scan)
    out = tmp_path / "out"
    args = ["complete", str(tmp_path / "scan.npy"), "--checkpoint", str(scan_model)]
    assert main([*args, "--out", str(out), "--up", "z", "--device", "cpu"]) == 0
    said = capsys.readouterr().out
    assert "trained in the scan frame" in said and "scans z-up" in said
    assert str(out / "scan_missing.ply") in said and str(out / "scan_completed.ply") in said
    import pfnet

    expected = pfnet.complete(scan, str(scan_model), up="z", runtime="torch", device="cpu")
    np.testing.assert_allclose(
        read_point_cloud(out / "scan_missing.ply"), expected.missing, atol=1e-5
    )


def test_scan_frame_training_samples(tiny_dataset):
    from pfnet.data.dataset import CompletionDataset

    shape = CompletionDataset(tiny_dataset, "train", crop="viewpoint")
    scan = CompletionDataset(tiny_dataset, "train", crop="viewpoint", frame="scan")
    a, b = shape[(0, 0)], scan[(0, 0)]
    partial = b["partial"].numpy().astype(np.float64)
    np.testing.assert_allclose(partial.mean(axis=0), 0, atol=1e-5)
    assert np.linalg.norm(partial, axis=1).max() == pytest.approx(1.0, abs=1e-5)
    # the same crop, mapped by the partial's frame: missing and complete follow the partial
    frame = scan_normalisation(a["partial"].numpy())
    np.testing.assert_allclose(b["missing"].numpy(), frame.apply(a["missing"].numpy()), atol=1e-5)
    assert float(b["frame_radius"]) == pytest.approx(frame.radius, rel=1e-6)
    assert float(a["frame_radius"]) == 1.0
    # the test crop of a scan-frame validation set is turned by the protocol's angle
    val = CompletionDataset(tiny_dataset, "test", crop="test", frame="scan", up_axis=1)
    plain = CompletionDataset(tiny_dataset, "test", crop="test")
    turned = plain[1]["partial"].numpy().astype(np.float64) @ up_rotation(scan_angle(1), 1).T
    np.testing.assert_allclose(
        val[1]["partial"].numpy(), scan_normalisation(turned).apply(turned), atol=1e-5
    )
    with pytest.raises(ConfigError, match="frame must be one of shape, scan, aligned"):
        CompletionDataset(tiny_dataset, "train", frame="world")


def test_aligned_frame_removes_the_heading():
    from pfnet.data.scan_frame import scan_frame

    rng = np.random.default_rng(3)
    cloud = rng.normal(size=(400, 3)) * [3.0, 1.0, 0.5] + [5.0, -2.0, 1.0]
    cloud[:, 0] += (cloud[:, 0] > 5.0) * 1.5  # one end reaches further: the sign is defined
    frame = scan_frame(cloud, aligned=True)
    seen = frame.apply(cloud)
    spread = np.cov(seen[:, [0, 2]].T)
    assert spread[0, 0] > spread[1, 1] and abs(spread[0, 1]) < 1e-6
    assert np.mean(seen[:, 0] ** 3) > 0
    np.testing.assert_allclose(frame.invert(seen), cloud, atol=1e-5)
    for angle in (0.4, 2.5, 5.0):
        turned = cloud @ up_rotation(angle, 1).T
        np.testing.assert_allclose(scan_frame(turned, aligned=True).apply(turned), seen, atol=1e-5)
    plain = scan_frame(cloud)
    np.testing.assert_array_equal(plain.rotation, np.eye(3))
    np.testing.assert_allclose(plain.apply(cloud), scan_normalisation(cloud).apply(cloud))


def test_the_aligned_end_frame_points_to_the_sparser_end_at_any_heading():
    from pfnet.data.scan_frame import END_SHARE, frame_of, scan_frame

    rng = np.random.default_rng(4)
    bar = rng.uniform([-2.0, -0.3, -0.3], [2.0, 0.3, 0.3], size=(600, 3))
    # a dense knob out at +x gives the third moment its sign and that end the more points,
    # so that the two rules point opposite ways
    knob = rng.normal([3.0, 0.0, 0.0], 0.05, size=(150, 3))
    bar = np.concatenate([bar, knob])
    moment = scan_frame(bar, aligned=True).apply(bar)
    end = scan_frame(bar, aligned=True, sign="end").apply(bar)
    assert np.mean(moment[:, 0] ** 3) > 0
    np.testing.assert_allclose(end[:, 0], -moment[:, 0], atol=1e-5)  # half a turn apart
    x = end[:, 0].astype(np.float64)
    reach = END_SHARE * (x.max() - x.min())
    assert (x > x.max() - reach).sum() <= (x < x.min() + reach).sum()  # +x: the sparser end
    for angle in (0.4, 2.5, 5.0):
        turned = bar @ up_rotation(angle, 1).T
        np.testing.assert_allclose(frame_of(turned, "aligned-end").apply(turned), end, atol=1e-4)
    np.testing.assert_allclose(frame_of(bar, "aligned").apply(bar), moment)
    np.testing.assert_array_equal(frame_of(bar, "scan").rotation, np.eye(3))
    with pytest.raises(ConfigError, match="sign must be moment, end or rim, got 'up'"):
        scan_frame(bar, aligned=True, sign="up")


@pytest.mark.parametrize("frame", ["aligned", "aligned-end"])
def test_an_aligned_model_completes_any_heading_alike(tmp_path, frame):
    import pfnet
    from pfnet.inference.checkpoint import save_checkpoint
    from pfnet.models import build_model
    from pfnet.training.config import preset_config

    config = preset_config("small").replace(n_points=512, frame=frame)
    torch.manual_seed(1)
    model = build_model(config).eval()
    path = tmp_path / "aligned.pt"
    save_checkpoint(path, {"config": config.to_dict(), "model": model.state_dict()})
    scan = _scan()
    first = pfnet.complete(scan, str(path), runtime="torch", device="cpu")
    assert first.frame == frame
    turn = up_rotation(1.1, 1)
    turned = pfnet.complete(scan @ turn.T, str(path), runtime="torch", device="cpu")
    np.testing.assert_allclose(turned.missing, first.missing @ turn.T, atol=1e-4)


def test_complete_command_keeps_a_survey_scan_in_double(scan_model, tmp_path):
    from pfnet.cli import main
    from pfnet.io.clouds import read_point_cloud, write_ply

    scan = _scan() + [512_345.0, 5_412_345.0, 230.0]  # float64, UTM-like
    write_ply(tmp_path / "survey.ply", scan)
    assert b"property double x" in (tmp_path / "survey.ply").read_bytes()[:300]
    out = tmp_path / "out"
    args = ["complete", str(tmp_path / "survey.ply"), "--checkpoint", str(scan_model)]
    assert main([*args, "--out", str(out), "--device", "cpu"]) == 0
    completed = read_point_cloud(out / "survey_completed.ply", keep_float64=True)
    assert completed.dtype == np.float64
    assert completed[: len(scan)].tobytes() == scan.tobytes()
    import pfnet

    expected = pfnet.complete(scan, str(scan_model), runtime="torch", device="cpu").missing
    np.testing.assert_allclose(completed[len(scan) :], expected, atol=1e-6)
