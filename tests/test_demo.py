"""Tests for ``pfnet demo``: the whole pipeline with a tiny budget on procedural shapes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

pytest.importorskip("torch")

import pfnet.inference.shipped  # noqa: E402
from pfnet.cli import main  # noqa: E402
from pfnet.inference.checkpoint import save_checkpoint  # noqa: E402
from pfnet.models import build_model  # noqa: E402
from pfnet.study import demo as demo_pipeline  # noqa: E402
from pfnet.training.config import preset_config  # noqa: E402


def _ship_a_512_point_model(folder):
    """An untrained 512-point model file standing in for the shipped default model."""
    config = preset_config("small").replace(n_points=512, width=0.125)
    checkpoint = folder / "model.pt"
    save_checkpoint(
        checkpoint, {"config": config.to_dict(), "model": build_model(config).state_dict()}
    )
    pfnet.inference.checkpoint.write_shipped(
        checkpoint, folder / "weights" / f"{pfnet.inference.shipped.DEFAULT_MODEL}.safetensors"
    )


@pytest.mark.slow
def test_demo_end_to_end_falls_back_to_procedural(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(demo_pipeline, "SWEETHOME3D_FURNITURE", tmp_path / "no-furniture")
    _ship_a_512_point_model(tmp_path)
    monkeypatch.setattr(pfnet.inference.shipped, "WEIGHTS_DIR", tmp_path / "weights")
    out = tmp_path / "demo"
    args = ["demo", "--out", str(out), "--count", "3", "--points", "512", "--minutes", "0.01"]
    assert main([*args, "--gallery-count", "2"]) == 0
    text = capsys.readouterr().out
    assert "sudo apt-get install sweethome3d-furniture" in text
    assert "Using procedural shapes" in text
    assert "an epoch takes" in text and "training 2 epochs in all" in text
    for step in ("[1/6]", "[2/6]", "[3/6]", "[4/6]", "[5/6]", "[6/6]"):
        assert step in text
    # the shipped model's completions of the same test split, scored beside the run's
    assert "  shipped model " in text and "F-score@0.01" in text
    shipped = json.loads((out / "predictions-shipped" / "predictions.json").read_text())
    assert shipped["checkpoint"] == f"shipped:{pfnet.inference.shipped.DEFAULT_MODEL}"
    assert json.loads((out / "metrics-shipped.json").read_text())["mean"]["pred_to_gt"] > 0
    assert (out / "data" / "manifest.json").is_file()
    assert (out / "gallery.png").read_bytes()[:4] == b"\x89PNG"
    report = json.loads((out / "metrics.json").read_text())
    assert report["region"] == "missing" and report["missing"] == []
    assert report["mean"]["pred_to_gt"] > 0
    predictions = json.loads((out / "predictions" / "predictions.json").read_text())
    assert predictions["n_samples"] == sum(c["n"] for c in report["categories"].values())
    assert f"checkpoint    {out / 'run'}" in text

    # A second run reuses the data set and trains into a fresh run folder; with no shipped
    # model it says so and skips the comparison.
    monkeypatch.setattr(pfnet.inference.shipped, "WEIGHTS_DIR", tmp_path / "nothing")
    assert main([*args[:-2], "--epochs", "1", "--procedural"]) == 0
    text = capsys.readouterr().out
    assert "reusing the data set" in text and str(out / "run-2") in text
    assert "no shipped model" in text and "skipping the comparison" in text


def test_demo_argument_errors(tmp_path, capsys):
    out = str(tmp_path / "d")
    assert main(["demo", "--out", out, "--minutes", "0"]) == 1
    assert "--minutes must be positive" in capsys.readouterr().err
    assert main(["demo", "--out", out, "--epochs", "0"]) == 1
    assert "--epochs must be at least 1" in capsys.readouterr().err
    assert main(["demo", "--out", out, "--source", str(tmp_path / "none")]) == 1
    assert "does not exist" in capsys.readouterr().err
    pytest.importorskip("torch")  # the data set is built after the device is resolved
    # Audit 11 (N4): 2 shapes a category leave no test split; refused before any training.
    args = ["demo", "--out", out, "--count", "2", "--points", "512", "--procedural"]
    assert main([*args, "--device", "cpu"]) == 1
    err = capsys.readouterr().err
    assert "has no shapes in its test split; the demo trains on one and completes" in err
    assert not (Path(out) / "run").exists()
    # Audit 11 (N3): the demo's folder is its own, never a data set, predictions or a run
    for marker, kind in (("manifest.json", "a prepared data set"), ("last.pt", "a training run")):
        other = tmp_path / marker.replace(".", "-")
        other.mkdir()
        (other / marker).write_text("{}")
        assert main(["demo", "--out", str(other), "--device", "cpu"]) == 1
        assert f"--out {other} is {kind}; name a folder for the demo" in capsys.readouterr().err
        assert [p.name for p in other.iterdir()] == [marker]


def test_the_budget_is_filled_with_epochs_timed_after_start_up():
    # 60 s left at 2.5 s an epoch: 24 more after the two timed ones; capped at 3x the preset.
    assert demo_pipeline.epochs_for_budget(60.0, 2.5, 30) == 26
    assert demo_pipeline.epochs_for_budget(600.0, 2.5, 30) == 90
    assert demo_pipeline.epochs_for_budget(-5.0, 2.5, 30) == 2  # start-up ate the budget
    assert demo_pipeline.epochs_for_budget(10.0, 0.0, 30) == 90
