"""Tests for ``pfnet predict``: files, determinism, agreement with the model, errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from pfnet.cli import main  # noqa: E402
from pfnet.data import load_split, test_protocol_crop  # noqa: E402
from pfnet.errors import ConfigError, DataError  # noqa: E402
from pfnet.inference.checkpoint import save_checkpoint  # noqa: E402
from pfnet.inference.devices import inference_device  # noqa: E402
from pfnet.inference.predict import predict_split  # noqa: E402
from pfnet.models import build_model  # noqa: E402
from pfnet.training.config import preset_config  # noqa: E402


def make_checkpoint(path, n_points: int, model: str = "pfnet", seed: int = 0, frame: str = "shape"):
    """An untrained but deterministic small model saved as a pfnet checkpoint (in the
    paper's shape frame unless ``frame`` says otherwise)."""
    config = preset_config("small").replace(n_points=n_points, model=model, frame=frame)
    torch.manual_seed(seed)
    generator = build_model(config).eval()
    save_checkpoint(path, {"config": config.to_dict(), "model": generator.state_dict()})
    return generator, config


@pytest.fixture(scope="module")
def checkpoint(tiny_dataset, tmp_path_factory):
    n_points = load_split(tiny_dataset, "test").points.shape[1]
    path = tmp_path_factory.mktemp("ckpt") / "model.pt"
    generator, config = make_checkpoint(path, n_points)
    return path, generator, config


def test_predict_writes_one_file_per_sample(tmp_path, tiny_dataset, checkpoint, capsys):
    path, generator, config = checkpoint
    out = tmp_path / "pred"
    code = main(
        ["predict", "--checkpoint", str(path), "--data", str(tiny_dataset), "--out", str(out)]
        + ["--batch-size", "3", "--device", "cpu"]
    )
    assert code == 0
    assert "pfnet evaluate" in capsys.readouterr().out
    clouds = load_split(tiny_dataset, "test")
    partial, _ = test_protocol_crop(np.asarray(clouds.points), config.missing_ratio)
    with torch.inference_mode():
        expected = generator(torch.from_numpy(np.asarray(partial, np.float32))).detail.numpy()
    for i, (cat, name) in enumerate(zip(clouds.category, clouds.name, strict=True)):
        pred = np.load(out / str(cat) / f"{name}.npy")
        assert pred.dtype == np.float32 and pred.shape == (config.n_missing, 3)
        np.testing.assert_allclose(pred, expected[i], rtol=1e-5, atol=1e-5)
    info = json.loads((out / "predictions.json").read_text())
    assert info["checkpoint"] == str(path.resolve())
    assert info["data"] == str(tiny_dataset.resolve())
    assert info["split"] == "test" and info["n_samples"] == len(clouds)
    assert info["protocol"]["missing_ratio"] == config.missing_ratio
    assert info["protocol"]["n_missing"] == config.n_missing
    assert info["model"]["name"] == "pfnet" and info["model"]["n_predicted"] == config.n_missing
    files = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file())
    assert len(files) == len(clouds) + 1  # nothing but the predictions and predictions.json

    # The files score through pfnet evaluate without a missing or unreadable one.
    assert main(["evaluate", str(out), "--data", str(tiny_dataset)]) == 0


def test_evaluate_refuses_other_clouds_under_the_same_names(
    tmp_path, tiny_dataset, checkpoint, capsys
):
    """Audit 12 note N1: a copy of the data set with other test clouds under the same names
    was scored silently; the record holds the digest of the split file predicted from."""
    import hashlib
    import shutil

    path, _, _ = checkpoint
    out, copy = tmp_path / "pred", tmp_path / "copy"
    args = ["predict", "--checkpoint", str(path), "--data", str(tiny_dataset), "--out", str(out)]
    assert main([*args, "--device", "cpu"]) == 0
    info = json.loads((out / "predictions.json").read_text())
    test_file = (tiny_dataset / "test.npz").read_bytes()
    assert info["split_sha256"] == hashlib.sha256(test_file).hexdigest()
    shutil.copytree(tiny_dataset, copy)
    assert main(["evaluate", str(out), "--data", str(copy)]) == 0  # the same clouds elsewhere
    clouds = load_split(copy, "test")
    np.savez(
        copy / "test.npz",
        points=clouds.points[:, ::-1].copy(),
        category=clouds.category,
        name=clouds.name,
    )
    capsys.readouterr()
    assert main(["evaluate", str(out), "--data", str(copy)]) == 1
    err = capsys.readouterr().err
    assert f"{out} was predicted from other test clouds than those of {copy}" in err
    ignore = ["evaluate", str(out), "--data", str(copy), "--ignore-recorded-protocol"]
    assert main(ignore) == 0
    info["split_sha256"] = "not a digest"
    (out / "predictions.json").write_text(json.dumps(info))
    assert main(["evaluate", str(out), "--data", str(tiny_dataset)]) == 1
    assert '"split_sha256" must be a SHA-256 in hex, got "not a digest"' in capsys.readouterr().err


def test_predict_is_deterministic_and_batch_independent(tmp_path, tiny_dataset, checkpoint):
    path = checkpoint[0]
    a = predict_split(path, tiny_dataset, tmp_path / "a", batch_size=1, device="cpu")
    b = predict_split(path, tiny_dataset, tmp_path / "b", batch_size=64, device="cpu")
    assert a["n_samples"] == b["n_samples"]
    for file in (tmp_path / "a").rglob("*.npy"):
        other = tmp_path / "b" / file.relative_to(tmp_path / "a")
        np.testing.assert_allclose(np.load(file), np.load(other), rtol=1e-5, atol=1e-6)


def test_predict_other_missing_ratio_and_gallery(tmp_path, tiny_dataset, checkpoint):
    path, _, config = checkpoint
    out, png = tmp_path / "pred", tmp_path / "g.png"
    args = ["predict", "--checkpoint", str(path), "--data", str(tiny_dataset), "--out", str(out)]
    assert main([*args, "--missing-ratio", "0.5", "--gallery", str(png)]) == 0
    info = json.loads((out / "predictions.json").read_text())
    assert info["protocol"]["missing_ratio"] == 0.5
    assert info["model"]["missing_ratio"] == config.missing_ratio
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_predict_errors(tmp_path, tiny_dataset, checkpoint, capsys, monkeypatch):
    path = checkpoint[0]
    base = ["predict", "--data", str(tiny_dataset), "--out", str(tmp_path / "o")]
    assert main([*base, "--checkpoint", str(tmp_path / "none.pt")]) == 1
    assert "none.pt does not exist" in capsys.readouterr().err
    (tmp_path / "junk.pt").write_bytes(b"junk")
    assert main([*base, "--checkpoint", str(tmp_path / "junk.pt")]) == 1
    assert "junk.pt cannot be read" in capsys.readouterr().err
    assert main([*base, "--checkpoint", str(path), "--batch-size", "0"]) == 1
    assert "--batch-size must be at least 1" in capsys.readouterr().err
    assert main([*base, "--checkpoint", str(path), "--missing-ratio", "1.5"]) == 1
    assert r"--missing-ratio must be in (0, 1)" in capsys.readouterr().err
    assert main([*base, "--checkpoint", str(path), "--split", "nope"]) == 1
    assert "nope" in capsys.readouterr().err
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for name in ("cuda", "cuda:1"):
        with pytest.raises(ConfigError, match=f"device {name}: this machine has 0 CUDA device"):
            inference_device(name)
    assert inference_device("auto") == "cpu" and inference_device("cpu") == "cpu"
    with pytest.raises(ConfigError, match="device must be auto, cpu, cuda or cuda:N, got 'tpu'"):
        inference_device("tpu")
    assert main([*base, "--checkpoint", str(path), "--device", "cuda:0"]) == 1
    assert "this machine has 0 CUDA device(s)" in capsys.readouterr().err


def test_two_runs_into_one_folder_never_mix(tmp_path, tiny_dataset, checkpoint, capsys):
    """Audit 13, C1: two predict runs into one folder at once both reported success over a
    mix of their files. A run holds the folder (flock) from its first file to its record, and
    one that finds a record written since it checked the folder writes nothing."""
    import subprocess
    import sys

    from pfnet.evaluation.prediction_folder import check_prediction_folder, open_prediction_folder
    from pfnet.evaluation.prediction_record import run_files

    path, _, _ = checkpoint
    out = tmp_path / "pred"
    args = ["predict", "--checkpoint", str(path), "--data", str(tiny_dataset), "--out", str(out)]
    assert main([*args, "--device", "cpu"]) == 0
    before = sorted(p.relative_to(out) for p in out.rglob("*"))
    holder = subprocess.Popen(  # another run, between its first file and its record
        [
            sys.executable,
            "-c",
            "import fcntl, os, sys, time; fd = os.open(sys.argv[1], os.O_RDONLY); "
            "fcntl.flock(fd, fcntl.LOCK_EX); print('held', flush=True); time.sleep(60)",
            str(out),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline() == "held\n"
        capsys.readouterr()
        assert main([*args, "--device", "cpu"]) == 1
        err = capsys.readouterr().err
        assert f"writing predictions into {out.resolve()}: it is in use by pid {holder.pid}" in err
    finally:
        holder.kill()
        holder.communicate()  # reaps it and closes its pipe
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == before
    # a run that finished while this one predicted: its record is newer than the check
    clouds = load_split(tiny_dataset, "test")
    check_prediction_folder(out, tiny_dataset, "test", "test", False)
    assert main([*args, "--device", "cpu"]) == 0  # the other run
    with pytest.raises(DataError, match="another pfnet predict wrote into .* while this one ran"):
        open_prediction_folder(
            out,
            run_files(clouds.category, clouds.name),
            "test",
            {"name": "test", "missing_ratio": 0.25},
            data_dir=tiny_dataset,
        )
    assert main([*args, "--device", "cpu"]) == 0  # the folder is free again


@pytest.mark.parametrize("frame", ["scan", "aligned"])
def test_predict_gives_a_scan_frame_model_each_partial_in_its_own_frame(
    tmp_path, tiny_dataset, frame
):
    from pfnet.inference.completion import complete_clouds

    n_points = load_split(tiny_dataset, "test").points.shape[1]
    generator, config = make_checkpoint(tmp_path / "scan.pt", n_points, frame=frame)
    record = predict_split(tmp_path / "scan.pt", tiny_dataset, tmp_path / "pred", device="cpu")
    assert record["protocol"]["input_frame"] == frame
    clouds = load_split(tiny_dataset, "test")
    partial, _ = test_protocol_crop(np.asarray(clouds.points), config.missing_ratio)
    # what `complete` returns for the same partial, in the data set's frame
    expected = complete_clouds(generator, list(partial), frame=frame)
    for i, (cat, name) in enumerate(zip(clouds.category, clouds.name, strict=True)):
        pred = np.load(tmp_path / "pred" / str(cat) / f"{name}.npy")
        np.testing.assert_allclose(pred, expected[i], atol=1e-5)
