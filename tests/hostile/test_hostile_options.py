"""Silent acceptance: options that contradict what a folder records, and unbounded numbers,
are refused with a line that says what to do."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from forge import write_predictions

from pfnet.cli import main
from pfnet.io.clouds import write_ply


def test_evaluate_follows_the_recorded_protocol_and_refuses_another(
    tmp_path: Path, tiny_dataset: Path, capsys
) -> None:
    pred = write_predictions(tmp_path / "pred", tiny_dataset, ratio=0.5, record=True)
    base = ["evaluate", str(pred), "--data", str(tiny_dataset)]
    assert main(base) == 0  # the recorded 50 %: each prediction is its own missing region
    out = capsys.readouterr().out
    assert "50% missing" in out
    assert main([*base, "--missing-ratio", "0.7"]) == 1
    err = capsys.readouterr().err
    assert "was predicted with 0.5 missing" in err and "--ignore-recorded-protocol" in err
    assert main([*base, "--split", "val"]) == 1
    assert "predictions of the 'test' split" in capsys.readouterr().err
    assert main([*base, "--missing-ratio", "0.7", "--ignore-recorded-protocol"]) == 0
    assert "70% missing" in capsys.readouterr().out
    (pred / "predictions.json").write_text("{broken")
    assert main(base) == 1
    assert "cannot read" in capsys.readouterr().err


def test_resume_refuses_another_data_set(tmp_path: Path, tiny_dataset: Path, capsys) -> None:
    pytest.importorskip("torch")
    other = tmp_path / "other"
    assert (
        main(["prepare", "procedural", "--out", str(other), "--count", "9", "--points", "512"]) == 0
    )
    moved = tmp_path / "moved"
    shutil.copytree(tiny_dataset, moved)
    run = tmp_path / "run"
    args = ["train", "--out", str(run), "--preset", "small", "--width", "0.125", "--device", "cpu"]
    assert main([*args, "--data", str(moved), "--epochs", "1"]) == 0
    capsys.readouterr()
    assert (
        main(["train", "--out", str(run), "--data", str(other), "--resume", "--epochs", "2"]) == 1
    )
    err = capsys.readouterr().err
    assert "trained on another data set" in err and str(moved.resolve()) in err
    shutil.move(moved, tmp_path / "moved-again")  # the same data elsewhere is fine
    resume = ["train", "--out", str(run), "--resume", "--epochs", "2", "--device", "cpu"]
    assert main([*resume, "--data", str(tmp_path / "moved-again")]) == 0


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["render", "{cloud}", "--out", "{png}", "--point-size", "nan"], "--point-size must be in"),
        (["render", "{cloud}", "--out", "{png}", "--point-size", "-1"], "--point-size must be in"),
        (["render", "{cloud}", "--out", "{png}", "--views", "10000"], "--views must be in"),
        (["demo", "--out", "{dir}", "--minutes", "nan"], "--minutes must be positive"),
        (["demo", "--out", "{dir}", "--minutes", "inf"], "--minutes must be positive"),
        (["prepare", "procedural", "--out", "{dir}", "--workers", "1000"], "workers must be"),
    ],
)
def test_unbounded_numbers_are_refused(
    tmp_path: Path, argv: list[str], message: str, capsys
) -> None:
    cloud = tmp_path / "c.ply"
    write_ply(cloud, np.random.default_rng(0).normal(size=(50, 3)).astype(np.float32))
    values = {"cloud": str(cloud), "png": str(tmp_path / "x.png"), "dir": str(tmp_path / "d")}
    assert main([a.format(**values) for a in argv]) == 1
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not (tmp_path / "x.png").exists() and not (tmp_path / "d").exists()
