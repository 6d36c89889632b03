"""The thirteenth hostile audit's breaks: config files that are not UTF-8 TOML tables (X4),
runs sized twice through a config file (V4), seeds beyond 2**63 (V2), a training run as the
prediction folder (P4), two demo sources (V3), names equal but for Unicode normalisation
(B2)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from brute import needs_runtime

from pfnet.cli import main


@pytest.mark.parametrize(
    "content, message",
    [
        (b"\xff\xfe\x00a", "is not valid TOML: 'utf-8' codec can't decode"),
        ("epochs = 3".encode("utf-16"), "is not valid TOML"),
        (b"train = 5\n", r"\[train\] must be a table of keys"),
        (b"train = [1, 2]\n", r"\[train\] must be a table of keys"),
        (b"epochs = 3\nsteps = 1\n", "epochs and steps size the run two ways"),
        (b"[train]\nepochs = 3\nsteps = 1\n", "epochs and steps size the run two ways"),
    ],
)
def test_config_files_that_are_not_one_plan_are_one_line(
    tmp_path: Path, tiny_dataset: Path, content: bytes, message: str, capsys
) -> None:
    config = tmp_path / "c.toml"
    config.write_bytes(content)
    out = tmp_path / "run"
    args = ["train", "--data", str(tiny_dataset), "--out", str(out), "--config", str(config)]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert err.startswith("pfnet train: error: config file") and re.search(message, err), err
    assert not out.exists()


def test_epochs_on_the_command_line_with_a_config_in_steps(
    tmp_path: Path, tiny_dataset: Path, capsys
) -> None:
    config = tmp_path / "steps.toml"
    config.write_text("steps = 1\n")
    out = tmp_path / "run"
    args = ["train", "--data", str(tiny_dataset), "--out", str(out), "--config", str(config)]
    assert main([*args, "--epochs", "3"]) == 1
    assert "--epochs with a config file that sizes the run in steps" in capsys.readouterr().err
    assert not out.exists()


def test_seeds_beyond_two_to_the_63_are_refused_before_any_work(tmp_path: Path, capsys) -> None:
    huge = str(2**64)
    out = tmp_path / "data"
    assert main(["prepare", "procedural", "--out", str(out), "--seed", huge]) == 1
    assert "seed must be an integer in [0, 2**63), got 1844674407" in capsys.readouterr().err
    demo = tmp_path / "demo"
    assert main(["demo", "--out", str(demo), "--procedural", "--seed", huge]) == 1
    assert "--seed must be an integer in [0, 2**63)" in capsys.readouterr().err
    assert main(["demo", "--out", str(demo), "--procedural", "--source", str(tmp_path)]) == 1
    assert "--procedural and --source name two sources" in capsys.readouterr().err
    assert not out.exists() and not demo.exists()


def test_predict_refuses_a_training_run_as_its_folder(
    tmp_path: Path, tiny_dataset: Path, capsys
) -> None:
    run = tmp_path / "run"
    run.mkdir()
    (run / "last.pt").write_bytes(b"a run's checkpoint")
    assert main(["predict", "--data", str(tiny_dataset), "--out", str(run)]) == 1
    assert f"--out {run} is a training run; name another folder" in capsys.readouterr().err
    assert [p.name for p in run.iterdir()] == ["last.pt"]


def test_names_equal_but_for_unicode_normalisation_are_refused() -> None:
    from pfnet.data.format import CloudSet
    from pfnet.errors import DataError

    points = np.zeros((2, 4, 3), np.float32)
    with pytest.raises(DataError, match="differ only in case or Unicode normalisation"):
        CloudSet(points, np.array(["chair", "chair"]), np.array(["\u00e9", "e\u0301"]))
    with pytest.raises(DataError, match="categories .* differ only in case or Unicode"):
        CloudSet(points, np.array(["caf\u00e9", "cafe\u0301"]), np.array(["a", "b"]))


def test_npy_headers_are_parsed_one_thread_at_a_time(tmp_path: Path, monkeypatch) -> None:
    """CPython 3.11's ast.literal_eval, which numpy parses .npy headers with, failed in two
    threads at once ("AST constructor recursion depth mismatch") while evaluate read
    predictions on its thread pool: the header reads hold one lock."""
    from numpy.lib import format as npy_format

    from pfnet.io.clouds import read_point_cloud
    from pfnet.io.formats import npy

    held = []
    original = npy_format.read_array_header_1_0

    def watched(fh, *args, **kwargs):
        held.append(npy.HEADER_LOCK.locked())
        return original(fh, *args, **kwargs)

    monkeypatch.setattr(npy_format, "read_array_header_1_0", watched)
    path = tmp_path / "cloud.npy"
    np.save(path, np.ones((5, 3), np.float32))
    assert read_point_cloud(path).shape == (5, 3)
    assert held and all(held)


def test_reports_go_into_a_folder_not_yet_there(tmp_path: Path, tiny_dataset: Path) -> None:
    """Audit 14 note: `evaluate --json` into a folder not yet there failed after the scoring
    (galleries make theirs); and `complete` left an empty --out when none of its inputs could
    be read (below)."""
    from forge import write_predictions

    pred = write_predictions(tmp_path / "pred", tiny_dataset)
    reports = tmp_path / "reports" / "deeper"
    args = ["evaluate", str(pred), "--data", str(tiny_dataset)]
    assert main([*args, "--json", str(reports / "r.json"), "--csv", str(reports / "r.csv")]) == 0
    assert sorted(p.name for p in reports.iterdir()) == ["r.csv", "r.json"]


@needs_runtime
def test_a_complete_that_read_nothing_leaves_no_folder(tmp_path: Path, capsys) -> None:
    bad = tmp_path / "bad.xyz"
    bad.write_text("not a point\n")
    out = tmp_path / "completed"
    assert main(["complete", str(bad), "--out", str(out)]) == 2
    captured = capsys.readouterr()
    assert "completed none of 1 file(s); nothing written" in captured.out
    assert "bad.xyz" in captured.err and not out.exists()
