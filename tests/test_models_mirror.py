"""PF-Net + mirror (pfnet.models.mirror): the plane search against a naive reference, the
encoder's input, growing from a trained PF-Net, and fine-tuning through the training loop's
init_from."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from pfnet.errors import ConfigError  # noqa: E402
from pfnet.models import ModelConfig, build_model  # noqa: E402
from pfnet.models.layers import gather_points, multi_resolution_indices  # noqa: E402
from pfnet.models.mirror import (  # noqa: E402
    GRID,
    IN_CHANNELS,
    N_ANGLES,
    OFFSETS,
    MirrorEncoder,
    PFNetMirror,
    _lookup,
    _occupancy,
)
from pfnet.models.pfnet import PFNetVanilla  # noqa: E402


def _symmetric_cloud(seed: int, normal_angle: float, offset: float, n: int = 1024) -> np.ndarray:
    """A random half-cloud and its mirror image across the vertical plane whose normal is at
    ``normal_angle`` in the x-z plane and whose offset is ``offset``: (n, 3) in the unit ball."""
    rng = np.random.default_rng(seed)
    normal = np.array([math.cos(normal_angle), 0.0, math.sin(normal_angle)])
    half = rng.uniform(-0.45, 0.45, size=(n // 2, 3))
    # keep one side of the plane: the image is then the other side
    side = half @ normal - offset
    half[side < 0] -= 2 * side[side < 0, None] * normal
    image = half - 2 * (half @ normal - offset)[:, None] * normal
    return np.concatenate([half, image]).astype(np.float32)


def _planes(cloud: np.ndarray):
    partial = torch.from_numpy(cloud)[None]
    indices = torch.from_numpy(multi_resolution_indices(partial))
    samples = gather_points(partial, indices[:, :128])
    return MirrorEncoder().planes(partial, samples)


def test_occupancy_lookup_matches_a_naive_voxel_set():
    rng = np.random.default_rng(1)
    cloud = rng.uniform(-1.2, 1.2, size=(300, 3)).astype(np.float32)  # some outside the cube
    near = cloud[:250] + rng.normal(0.0, 0.002, size=(250, 3))  # most in an occupied voxel
    queries = np.concatenate([near, rng.uniform(-1.2, 1.2, size=(250, 3))]).astype(np.float32)
    size = 2.0 / GRID

    def voxel(p):
        return tuple(int(math.floor((c + 1.0) / size)) for c in p)

    occupied = {voxel(p) for p in cloud if all(0 <= v < GRID for v in voxel(p))}
    expected = [float(voxel(q) in occupied) for q in queries]
    grid = _occupancy(torch.from_numpy(cloud)[None], torch.zeros(1, GRID**3 + 1))
    found = _lookup(grid, torch.from_numpy(queries)[None])[0]
    assert found.tolist() == expected
    assert 80 < sum(expected) < 400  # the check saw both kinds of points


@pytest.mark.parametrize(("step", "offset_step"), [(0, 4), (6, -3), (15, 0)])
def test_the_plane_search_finds_a_planted_mirror_plane(step, offset_step):
    angle = step * math.pi / N_ANGLES
    # the offset is measured from the cloud's centroid, which lies on the plane here
    cloud = _symmetric_cloud(step, angle, offset_step * OFFSETS[1] * 0.0)
    normals, offsets, shares, _ = _planes(cloud)
    expected = np.array([math.cos(angle), 0.0, math.sin(angle)])
    assert abs(float(normals[0, 0] @ torch.from_numpy(expected).float())) > 0.99
    assert float(shares[0, 0]) > 0.9
    # the plane passes through the centroid (within one offset step)
    centre = cloud.mean(axis=0)
    assert abs(float(offsets[0, 0]) - float(centre @ normals[0, 0].numpy())) <= OFFSETS[9]
    # the second plane is at least 30 degrees away and scores less
    cos = abs(float(normals[0, 0] @ normals[0, 1]))
    assert cos < math.cos(math.radians(29.9))
    assert float(shares[0, 1]) <= float(shares[0, 0])


def test_the_plane_search_finds_an_off_centre_plane():
    # a piece cut off one side moves the centroid off the plane, as in a partial scan
    cloud = _symmetric_cloud(3, 0.0, 0.1)
    cloud = cloud[cloud[:, 0] > -0.3]
    normals, offsets, shares, _ = _planes(cloud)
    assert abs(float(normals[0, 0, 0])) > 0.99
    assert float(offsets[0, 0]) * math.copysign(1.0, float(normals[0, 0, 0])) == pytest.approx(
        0.1, abs=0.04
    )


def test_the_encoder_reads_the_partial_and_half_as_many_mirror_points():
    encoder = MirrorEncoder(width=0.125)
    cloud = torch.from_numpy(_symmetric_cloud(0, 0.0, 0.0, n=64))[None]
    seen = []
    encoder.cmlps[0].register_forward_pre_hook(lambda module, args: seen.append(args[0]))
    encoder(cloud)
    features = seen[0]
    assert features.shape == (1, 64 + 32, IN_CHANNELS)
    original, mirrored = features[0, :64], features[0, 64:]
    assert torch.equal(original[:, :3], cloud[0]) and not original[:, 3:].any()
    assert torch.all(mirrored[:, 3] == 1)  # the flag
    assert set(mirrored[:, 4].tolist()) <= {0.0, 1.0}  # empty or not
    assert torch.all((mirrored[:, 5] > 0) & (mirrored[:, 5] <= 1))  # the plane's share


def test_a_forward_and_backward_pass_gives_the_missing_points():
    model = build_model(
        ModelConfig(model="pfnet-mirror", n_points=256, missing_ratio=0.5, width=0.125)
    )
    partial = torch.rand(2, 128, 3) * 2 - 1
    completion = model(partial)
    assert completion.detail.shape == (2, 128, 3)
    assert completion.primary.shape == (2, 64, 3) and completion.secondary.shape == (2, 128, 3)
    completion.detail.sum().backward()
    first = model.encoder.cmlps[0].mlp.layers[0][0].weight
    assert first.grad is not None and first.grad[:, 3:].abs().sum() > 0


def test_grow_from_copies_a_trained_pfnet_with_zero_mirror_weights():
    torch.manual_seed(0)
    trained = PFNetVanilla(n_points=256, n_missing=128, width=0.125)
    grown = PFNetMirror(n_points=256, n_missing=128, width=0.125)
    grown.grow_from(trained)
    source = trained.state_dict()
    for key, value in grown.state_dict().items():
        if value.shape == source[key].shape:
            assert torch.equal(value, source[key]), key
        else:
            assert torch.equal(value[:, :3], source[key]) and not value[:, 3:].any(), key
    wider = PFNetVanilla(n_points=256, n_missing=128, width=0.25)
    with pytest.raises(ValueError, match=r"weight encoder\..*another width"):
        grown.grow_from(wider)


def test_fine_tuning_grows_the_mirror_model_from_a_pfnet_checkpoint_only(tmp_path):
    from dataclasses import asdict

    from pfnet.inference.checkpoint import save_checkpoint
    from pfnet.training.config import TrainConfig
    from pfnet.training.resume import start_from

    sizes = dict(n_points=256, missing_ratio=0.5, width=0.125)

    def checkpoint(model: str) -> str:
        generator = build_model(ModelConfig(model=model, **sizes))
        path = tmp_path / f"{model}.pt"
        config = asdict(TrainConfig(model=model, **sizes))
        save_checkpoint(path, {"model": generator.state_dict(), "config": config})
        return str(path)

    run = dict(model="pfnet-mirror", **sizes)
    grown = build_model(ModelConfig(model="pfnet-mirror", **sizes))
    start_from(grown, TrainConfig(**run, init_from=checkpoint("pfnet-vanilla")))
    with pytest.raises(ConfigError, match=r"another network: model 'mlp'"):
        start_from(grown, TrainConfig(**run, init_from=checkpoint("mlp")))


@pytest.mark.slow
@pytest.mark.parametrize("name", ["pfnet-mirror", "pfnet-edge"])
def test_the_onnx_export_passes_the_graph_check_and_completes_a_scan(tmp_path, name):
    """The plane search (and pfnet-edge's neighbour search) exports without the operators the
    graph check refuses (ConstantOfShape, Range, open slice ends), so ONNX Runtime runs it as
    torch does."""
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnxscript")
    from pfnet.cli import main
    from pfnet.inference.checkpoint import save_checkpoint
    from pfnet.inference.onnx_graph import check_graph
    from pfnet.training.config import preset_config

    config = preset_config("small").replace(model=name, n_points=512, width=0.125)
    torch.manual_seed(0)
    model = build_model(config).eval()
    checkpoint = tmp_path / "mirror.pt"
    save_checkpoint(checkpoint, {"config": config.to_dict(), "model": model.state_dict()})
    onnx_file = tmp_path / "mirror.onnx"
    assert main(["export", "--checkpoint", str(checkpoint), "--out", str(onnx_file)]) == 0
    check_graph(onnx_file)
    scan = tmp_path / "scan.npy"
    np.save(scan, _symmetric_cloud(5, 0.3, 0.0, n=300) * 20.0 + 7.0)
    for runtime in ("torch", "onnx"):
        out = tmp_path / runtime
        argv = [
            "complete",
            str(scan),
            "--checkpoint",
            str(checkpoint if runtime == "torch" else onnx_file),
        ]
        assert main([*argv, "--out", str(out), "--runtime", runtime]) == 0
    from pfnet.io.clouds import read_point_cloud

    by_torch = read_point_cloud(tmp_path / "torch" / "scan_missing.ply")
    by_onnx = read_point_cloud(tmp_path / "onnx" / "scan_missing.ply")
    np.testing.assert_allclose(by_onnx, by_torch, atol=1e-4 * 20.0 * 2)
