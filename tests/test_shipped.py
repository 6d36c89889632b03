"""Shipped models: the model file format, names as --checkpoint, `pfnet models`, and the
default model that `complete` and `predict` use with no --checkpoint."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import pfnet.inference.shipped  # noqa: E402
from pfnet.cli import main  # noqa: E402
from pfnet.errors import ConfigError, DataError  # noqa: E402
from pfnet.inference.checkpoint import load_checkpoint, save_checkpoint, write_shipped  # noqa: E402
from pfnet.inference.shipped import DEFAULT_MODEL, read_metadata, resolve_checkpoint, shipped_models  # noqa: E402
from pfnet.io.clouds import read_point_cloud, write_ply  # noqa: E402
from pfnet.models import build_model  # noqa: E402
from pfnet.training.config import preset_config  # noqa: E402

CARD = {"summary": "a test model", "test": {"data": "nothing", "cd_l2": 1.5, "f_score": 0.25}}


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    config = preset_config("small").replace(n_points=512, width=0.125)
    torch.manual_seed(0)
    model = build_model(config)
    model.train()
    with torch.no_grad():  # give BatchNorm non-trivial running statistics
        model(torch.randn(8, 384, 3))
    path = tmp_path_factory.mktemp("ckpt") / "best.pt"
    save_checkpoint(path, {"config": config.to_dict(), "model": model.state_dict()})
    return path


@pytest.fixture
def weights_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, checkpoint: Path) -> Path:
    """A weights folder holding the test model as ``tiny`` and as the default model."""
    folder = tmp_path / "weights"
    monkeypatch.setattr(pfnet.inference.shipped, "WEIGHTS_DIR", folder)
    write_shipped(checkpoint, folder / "tiny.safetensors", card=CARD)
    write_shipped(checkpoint, folder / f"{DEFAULT_MODEL}.safetensors", card=CARD)
    return folder


def test_model_file_round_trip_matches_the_checkpoint_within_float16(
    tmp_path: Path, checkpoint: Path
) -> None:
    path = write_shipped(checkpoint, tmp_path / "m.safetensors", card=CARD)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
    config, card = read_metadata(path)
    assert card == CARD and config["width"] == 0.125
    shipped, _ = load_checkpoint(path)
    original, _ = load_checkpoint(checkpoint)
    assert all(p.dtype == torch.float32 for p in shipped.parameters())
    assert not shipped.training
    x = torch.rand(4, 384, 3) - 0.5
    with torch.no_grad():
        a, b = shipped(x).detail, original(x).detail
    assert a.shape == (4, 128, 3)
    # float16 weights: relative error 2**-11 per weight; coordinates are O(1)
    assert torch.allclose(a, b, atol=2e-3), (a - b).abs().max()
    assert not torch.equal(a, b)  # the weights really were stored as float16
    assert path.stat().st_size < 0.6 * checkpoint.stat().st_size
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask  # as any file written here


def test_a_model_file_gets_a_new_card_and_keeps_its_weights(
    tmp_path: Path, checkpoint: Path
) -> None:
    first = write_shipped(checkpoint, tmp_path / "first.safetensors", card=CARD)
    card = {"summary": "the same weights, measured again"}
    second = write_shipped(first, tmp_path / "second.safetensors", card=card)
    assert read_metadata(second) == (read_metadata(first)[0], card)
    a, b = pfnet.inference.shipped.load_weights(first), pfnet.inference.shipped.load_weights(second)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_names_resolve_to_shipped_files_and_paths_win(weights_dir: Path, tmp_path: Path) -> None:
    assert resolve_checkpoint("tiny") == weights_dir / "tiny.safetensors"
    assert resolve_checkpoint(None) == weights_dir / f"{DEFAULT_MODEL}.safetensors"
    local = tmp_path / "tiny"  # a file of the same name in the working folder wins
    local.write_bytes(b"")
    assert resolve_checkpoint(str(local)) == local
    assert pfnet.inference.shipped.describe(resolve_checkpoint("tiny")) == "shipped:tiny"
    assert [m.name for m in shipped_models()] == sorted(["tiny", DEFAULT_MODEL])


def test_unknown_names_and_bad_files_are_refused_by_name(weights_dir: Path, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"no checkpoint file 'nope' and no shipped model.*tiny"):
        resolve_checkpoint("nope")
    with pytest.raises(ConfigError, match=r"checkpoint .*runs/best.pt does not exist"):
        resolve_checkpoint(tmp_path / "runs" / "best.pt")
    with pytest.raises(ConfigError, match="is not a file"):
        resolve_checkpoint(tmp_path)
    garbage = tmp_path / "garbage.safetensors"
    garbage.write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{not json at all")
    with pytest.raises(DataError, match="garbage.safetensors cannot be read"):
        load_checkpoint(garbage)
    from safetensors.numpy import save_file

    foreign = tmp_path / "foreign.safetensors"
    save_file({"w": np.zeros(3, np.float32)}, str(foreign))
    with pytest.raises(DataError, match="foreign.safetensors is not a pfnet model file"):
        load_checkpoint(foreign)
    with pytest.raises(ConfigError, match="must end in .safetensors"):
        write_shipped(weights_dir / "tiny.safetensors", tmp_path / "model.bin")


def test_pfnet_models_lists_the_shipped_models(weights_dir: Path, capsys) -> None:
    assert main(["models"]) == 0
    out = capsys.readouterr().out
    assert f"{DEFAULT_MODEL}  (default)" in out and "tiny\n" in out
    assert "a test model" in out and "x1000 1.50, F-score@0.01 0.250" in out
    assert main(["models", "--json"]) == 0
    cards = json.loads(capsys.readouterr().out)
    assert [c["default"] for c in cards] == [
        name == DEFAULT_MODEL for name in sorted(["tiny", DEFAULT_MODEL])
    ]


def test_complete_and_predict_use_the_default_model_without_checkpoint(
    weights_dir: Path, tmp_path: Path, tiny_dataset: Path, capsys
) -> None:
    scan = tmp_path / "scan.ply"
    rng = np.random.default_rng(0)
    write_ply(scan, rng.normal(size=(700, 3)).astype(np.float32))
    assert main(["complete", str(scan), "--out", str(tmp_path / "done"), "--device", "cpu"]) == 0
    assert read_point_cloud(tmp_path / "done" / "scan_missing.ply").shape == (128, 3)
    pred = tmp_path / "pred"
    assert (
        main(["predict", "--data", str(tiny_dataset), "--out", str(pred), "--device", "cpu"]) == 0
    )
    info = json.loads((pred / "predictions.json").read_text())
    assert info["checkpoint"] == f"shipped:{DEFAULT_MODEL}"
    assert info["n_samples"] == 12


def test_the_shipped_default_model_completes_real_scans_with_no_checkpoint(
    tmp_path: Path, capsys
) -> None:
    """The installed package's own model file: no training run, no --checkpoint, no download.

    The scans are real catalogue chairs when Debian's sweethome3d-furniture is installed
    (else procedural chairs), cut as a scanner would see them, moved into scanner units and
    written as .xyz and binary .ply.
    """
    from pfnet.data import SWEETHOME3D_PATH, load_split, prepare_dataset
    from pfnet.geometry import crop_by_viewpoint

    models = {m.name: m for m in shipped_models()}
    assert DEFAULT_MODEL in models, "the default model file is missing from pfnet/weights"
    card = models[DEFAULT_MODEL].card
    assert card["test"]["cd_l2"] > 0 and card["train_data"]["licenses"]
    real = SWEETHOME3D_PATH.is_dir()
    data = tmp_path / "data"
    prepare_dataset(
        SWEETHOME3D_PATH if real else None,
        data,
        points=3000,
        categories=["chair"],
        count=None if real else 4,
        progress=False,
    )
    shapes = load_split(data, "test").points
    viewpoint = np.array([1.0, 0.0, 1.0], np.float32)
    scans = {}
    for k, name in enumerate(("scan.xyz", "scan2.ply")):
        partial, _ = crop_by_viewpoint(shapes[k % len(shapes)], viewpoint, n_missing=750)
        scans[name] = partial * 850.0 + np.array([1e4, -300.0, 52.0], np.float32)  # millimetres
    rows = "\n".join(" ".join(repr(float(v)) for v in p) for p in scans["scan.xyz"])
    (tmp_path / "scan.xyz").write_text(rows)
    write_ply(tmp_path / "scan2.ply", scans["scan2.ply"])
    out = tmp_path / "done"
    inputs = [str(tmp_path / name) for name in scans]
    assert main(["complete", *inputs, "--out", str(out), "--device", "cpu"]) == 0
    assert "completed 2 of 2" in capsys.readouterr().out
    for name, scan in scans.items():
        missing = read_point_cloud(out / f"{Path(name).stem}_missing.ply")
        assert missing.shape == (512, 3) and np.isfinite(missing).all()
        # the prediction is spread around the cut in the scan's own units, not a point
        low, high = scan.min(axis=0), scan.max(axis=0)
        assert np.all(missing.std(axis=0) > 0.01 * (high - low))
        assert np.all(missing.mean(axis=0) > low - 0.5 * (high - low))
        assert np.all(missing.mean(axis=0) < high + 0.5 * (high - low))
