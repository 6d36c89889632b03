"""ONNX export and the ONNX Runtime path: agreement with PyTorch, same files, no torch needed.

Tolerance: ONNX Runtime's detail points may differ from PyTorch's by at most
``TOLERANCE`` = 1e-4 in normalised coordinates (the unit ball; measured: ~1e-6), so by
``1e-4 * radius`` in a scan's own coordinates.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest

torch = pytest.importorskip("torch")
ort = pytest.importorskip("onnxruntime")
pytest.importorskip("onnxscript")

from pfnet.cli import main  # noqa: E402
from pfnet.data import load_split, test_protocol_crop  # noqa: E402
from pfnet.errors import ConfigError, DataError, MissingDependency  # noqa: E402
from pfnet.inference.checkpoint import load_checkpoint, save_checkpoint  # noqa: E402
from pfnet.inference.onnx_export import TOLERANCE  # noqa: E402
from pfnet.inference.onnx_graph import file_sha256  # noqa: E402
from pfnet.inference.runtimes import OnnxGenerator, has_module, load_generator  # noqa: E402
from pfnet.inference.shipped import DEFAULT_MODEL, WEIGHTS_DIR, read_metadata  # noqa: E402
from pfnet.io.clouds import read_point_cloud, write_ply  # noqa: E402
from pfnet.models import build_model  # noqa: E402
from pfnet.training.config import TrainConfig, preset_config  # noqa: E402

SHIPPED_ONNX = WEIGHTS_DIR / f"{DEFAULT_MODEL}.onnx"


def _scan(n: int, seed: int) -> np.ndarray:
    """A half sphere in arbitrary units and position (radius 37.5), float32."""
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(n, 3))
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    points[:, 0] = np.abs(points[:, 0])
    return (points * 37.5 + [100.0, -20.0, 3.0]).astype(np.float32)


@pytest.fixture(scope="module")
def exported(tiny_dataset, tmp_path_factory):
    """A deterministic untrained small PF-Net for 512-point clouds, as .pt and as .onnx."""
    n_points = load_split(tiny_dataset, "test").points.shape[1]
    config = preset_config("small").replace(n_points=n_points)
    torch.manual_seed(0)
    model = build_model(config).eval()
    folder = tmp_path_factory.mktemp("onnx")
    checkpoint = folder / "model.pt"
    save_checkpoint(checkpoint, {"config": config.to_dict(), "model": model.state_dict()})
    onnx_file = folder / "model.onnx"
    assert main(["export", "--checkpoint", str(checkpoint), "--out", str(onnx_file)]) == 0
    return checkpoint, onnx_file, model, config


def test_export_file(exported, capsys):
    checkpoint, onnx_file, _, config = exported
    generator = OnnxGenerator(onnx_file)
    assert generator.inputs == ["partial", "scale_indices"]
    assert (generator.n_points, generator.n_missing) == (config.n_points, config.n_missing)
    meta = generator.metadata
    assert meta["model"] == "pfnet" and meta["preset"] == "small"
    assert float(meta["width"]) == config.width
    assert json.loads(meta["config"]) == config.to_dict()
    assert meta["source_sha256"] == file_sha256(checkpoint)
    # dynamic batch and point axes
    shapes = [i.shape for i in generator.session.get_inputs()]
    assert all(isinstance(s[0], str) and isinstance(s[1], str) for s in shapes)


def test_onnx_matches_torch_any_batch_and_size(exported, tiny_dataset):
    _, onnx_file, model, config = exported
    generator = OnnxGenerator(onnx_file)
    clouds = np.asarray(load_split(tiny_dataset, "test").points)
    partial, _ = test_protocol_crop(clouds, config.missing_ratio)
    for batch in (partial[:1], partial, partial[:5, :301]):  # odd sizes too
        batch = np.ascontiguousarray(batch, np.float32)
        with torch.inference_mode():
            want = model(torch.from_numpy(batch)).detail.numpy()
        got = generator.predict(batch)
        assert got.shape == want.shape
        assert np.abs(got - want).max() <= TOLERANCE


def test_shipped_onnx_is_the_shipped_model(tiny_dataset):
    """The shipped ONNX file was exported from the shipped weights and completes as they do."""
    onnx_run = load_generator(None, runtime="onnx", device="cpu")
    torch_run = load_generator(None, runtime="torch", device="cpu")
    assert onnx_run.model.path == SHIPPED_ONNX  # load_generator checked source_sha256
    config, _ = read_metadata(WEIGHTS_DIR / f"{DEFAULT_MODEL}.safetensors")
    assert onnx_run.config == torch_run.config == TrainConfig.from_dict(config).model_config()
    # float16-exact weights stored as float16: about the size of the safetensors file
    assert (
        SHIPPED_ONNX.stat().st_size
        < 1.1 * (WEIGHTS_DIR / f"{DEFAULT_MODEL}.safetensors").stat().st_size
    )
    n = torch_run.model.n_points - torch_run.model.n_missing
    clouds = np.asarray(load_split(tiny_dataset, "test").points)  # real-ish shapes of 512
    rng = np.random.default_rng(0)
    batch = clouds[:, rng.integers(0, clouds.shape[1], n)]  # resampled to the model's 1536
    batch = np.ascontiguousarray(batch / np.abs(batch).max(), np.float32)
    from pfnet.inference.predict import predict_missing

    got = predict_missing(onnx_run.model, batch, 5, "cpu")
    want = predict_missing(torch_run.model, batch, 5, "cpu")
    assert np.abs(got - want).max() <= TOLERANCE


@pytest.mark.parametrize("suffix", [".xyz", ".ply"])
def test_complete_same_files_on_both_runtimes(exported, tmp_path, suffix):
    _, onnx_file, _, _ = exported
    scan = tmp_path / f"scan{suffix}"
    points = _scan(700, seed=1)
    if suffix == ".ply":
        write_ply(scan, points)  # binary little-endian
    else:
        scan.write_text("\n".join(" ".join(repr(float(v)) for v in p) for p in points))
    outputs = {}
    for runtime, checkpoint in (("torch", onnx_file.with_suffix(".pt")), ("onnx", onnx_file)):
        out = tmp_path / runtime
        args = ["complete", str(scan), "--out", str(out), "--checkpoint", str(checkpoint)]
        assert main([*args, "--runtime", runtime]) == 0
        outputs[runtime] = [
            read_point_cloud(out / f"scan_{k}.ply") for k in ("missing", "completed")
        ]
    for a, b in zip(outputs["torch"], outputs["onnx"], strict=True):
        assert a.shape == b.shape
        assert np.abs(a - b).max() <= TOLERANCE * 37.5 * 1.01
    np.testing.assert_array_equal(outputs["onnx"][1][: len(points)], read_point_cloud(scan))


def test_predict_same_files_on_both_runtimes(exported, tiny_dataset, tmp_path):
    checkpoint, onnx_file, _, _ = exported
    for runtime, source in (("torch", checkpoint), ("onnx", onnx_file)):
        args = ["predict", "--checkpoint", str(source), "--data", str(tiny_dataset)]
        assert main([*args, "--out", str(tmp_path / runtime), "--runtime", runtime]) == 0
    if has_module("plotly"):  # the gallery as the HTML viewer
        args += ["--out", str(tmp_path / "again"), "--gallery", str(tmp_path / "g.html")]
        assert main([*args, "--gallery-count", "2"]) == 0
        assert (tmp_path / "g.html").read_text(encoding="utf-8").count('"method":"update"') == 2
    info = json.loads((tmp_path / "onnx" / "predictions.json").read_text())
    assert info["runtime"] == "onnx" and info["device"] == "cpu"
    files = sorted((tmp_path / "torch").glob("*/*.npy"))
    assert files and len(files) == len(list((tmp_path / "onnx").glob("*/*.npy")))
    for path in files:
        other = tmp_path / "onnx" / path.parent.name / path.name
        assert np.abs(np.load(path) - np.load(other)).max() <= TOLERANCE


def test_runtime_choices_and_errors(exported, tmp_path, monkeypatch):
    checkpoint, onnx_file, _, _ = exported
    assert load_generator(onnx_file).runtime == "onnx"  # auto: an .onnx file
    assert load_generator(checkpoint, device="cpu").runtime == "torch"  # auto with torch
    beside = load_generator(checkpoint, runtime="onnx")  # model.onnx beside model.pt
    assert beside.runtime == "onnx" and beside.model.path == onnx_file
    with pytest.raises(ConfigError, match="is an ONNX model"):
        load_generator(onnx_file, runtime="torch")
    with pytest.raises(ConfigError, match="no ONNX export.*pfnet export --checkpoint"):
        fresh = tmp_path / "fresh.pt"
        fresh.write_bytes(checkpoint.read_bytes())
        load_generator(fresh, runtime="onnx")
    # an ONNX file beside a checkpoint it was not exported from
    stale = tmp_path / "stale.pt"
    model, config = load_checkpoint(checkpoint)
    torch.manual_seed(1)
    save_checkpoint(stale, {"config": config.to_dict(), "model": build_model(config).state_dict()})
    (tmp_path / "stale.onnx").write_bytes(onnx_file.read_bytes())
    with pytest.raises(DataError, match="was not exported from"):
        load_generator(stale, runtime="onnx")
    bogus = tmp_path / "bogus.onnx"
    bogus.write_bytes(b"not onnx")
    with pytest.raises(DataError, match="cannot be read"):
        load_generator(bogus)
    # neither PyTorch nor ONNX Runtime: one line naming the extra
    monkeypatch.setitem(sys.modules, "torch", None)
    monkeypatch.setitem(sys.modules, "onnxruntime", None)
    with pytest.raises(MissingDependency, match=r"pip install onnxruntime \(the \[infer\] extra"):
        load_generator(None)


@pytest.mark.parametrize("options", [[], ["--no-check"]], ids=["checked", "no-check"])
def test_export_refuses_a_model_that_predicts_nan(exported, tmp_path, capsys, options):
    """Finite weights whose products overflow: complete and predict refuse the model, so
    export does too, with the same message, before writing anything."""
    checkpoint, _, _, _ = exported
    state = torch.load(checkpoint, weights_only=True)
    for value in state["model"].values():
        if value.is_floating_point() and value.dim() >= 2:
            value.fill_(3e37)
    overflowing = tmp_path / "overflow.pt"
    torch.save(state, overflowing)
    out = tmp_path / "overflow.onnx"
    assert main(["export", "--checkpoint", str(overflowing), "--out", str(out), *options]) == 1
    err = capsys.readouterr().err
    assert err == (
        f"pfnet export: error: model {overflowing} predicted NaN or infinite coordinates; "
        "it is not a working model (do its weights overflow?)\n"
    )
    assert list(tmp_path.iterdir()) == [overflowing]  # no .onnx, no temporary file


def test_no_runtime_installed_is_one_line(tmp_path, monkeypatch, capsys):
    scan = tmp_path / "scan.xyz"
    np.savetxt(scan, _scan(100, seed=2))
    monkeypatch.setitem(sys.modules, "torch", None)
    monkeypatch.setitem(sys.modules, "onnxruntime", None)
    assert main(["complete", str(scan), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "pip install onnxruntime" in err and "Traceback" not in err


TORCH_FREE = textwrap.dedent(
    """
    import sys
    sys.modules["torch"] = None  # any import of torch fails
    from pfnet.cli import main
    code = main(["complete", sys.argv[1], "--out", sys.argv[2]])
    assert code == 0, code
    print("torch-free ok")
    """
)


def test_complete_without_torch_uses_the_shipped_onnx(tmp_path):
    """``pfnet complete`` with no --checkpoint and no torch: the shipped model on ONNX Runtime."""
    scan = tmp_path / "scan.ply"
    write_ply(scan, _scan(900, seed=3))
    done = subprocess.run(
        [sys.executable, "-c", TORCH_FREE, str(scan), str(tmp_path / "onnx")],
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert "torch-free ok" in done.stdout
    assert main(["complete", str(scan), "--out", str(tmp_path / "torch"), "--device", "cpu"]) == 0
    for kind in ("missing", "completed"):
        a = read_point_cloud(tmp_path / "onnx" / f"scan_{kind}.ply")
        b = read_point_cloud(tmp_path / "torch" / f"scan_{kind}.ply")
        assert np.abs(a - b).max() <= TOLERANCE * 37.5 * 1.01
