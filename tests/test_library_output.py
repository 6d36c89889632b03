"""Only the commands print: the library returns what it made, or hands its notes to a
callback the command gives it (issue 35). And what the commands then say."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from pfnet.cli import main

PACKAGE = Path(__file__).resolve().parent.parent / "python" / "pfnet"

# print() calls still in the library, each with the reason no callback can carry it: none.
# What the library has to say as it works goes to a callback its caller gives (the training
# loop's notes, epoch lines and stop notice, the study's progress, a folder skipped while
# scoring, a data source the demo falls back from); this set may only stay empty.
STILL_PRINTING: set[str] = set()


def _printing_modules() -> set[str]:
    found = set()
    for path in PACKAGE.rglob("*.py"):
        relative = path.relative_to(PACKAGE).as_posix()
        if relative == "cli.py" or relative.startswith("commands/"):
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        calls = (n for n in ast.walk(tree) if isinstance(n, ast.Call))
        if any(isinstance(c.func, ast.Name) and c.func.id == "print" for c in calls):
            found.add(relative)
    return found


def test_only_the_commands_print():
    assert _printing_modules() <= STILL_PRINTING


def test_the_training_loop_hands_its_notes_to_the_command():
    import inspect

    pytest.importorskip("torch")  # the light install has no training loop

    from pfnet.training.loop import Trainer

    source = inspect.getsource(Trainer.run)
    assert "pfnet train:" not in source  # the command's name is the command's to print


@pytest.mark.parametrize(
    ("options", "noted"),
    [([], True), (["--preset", "small"], False), (["--preset", "paper"], False)],
)
def test_train_says_which_preset_it_uses_when_none_is_given(
    tmp_path, monkeypatch, capsys, options, noted
):
    pytest.importorskip("torch")
    import pfnet.training.loop

    seen = {}

    def fake_train(config, data, out, **kwargs):
        seen["preset_width"] = config.width
        kwargs["notes"]("only 3 of the run's 9 optimiser steps are at the full learning rate")
        return {
            "world_size": 1,
            "interrupted": False,
            "best_val_cd_l2": None,
            "epochs": 0,
            "best_epoch": 0,
        }

    monkeypatch.setattr(pfnet.training.loop, "train", fake_train)
    # --threads 1: no note of how many threads a busy machine leaves the run
    argv = ["train", "--data", str(tmp_path), "--out", str(tmp_path / "run"), "--threads", "1"]
    argv += options
    assert main(argv) == 0
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("pfnet train: note:")]
    assert ("training the `paper` preset" in err) == noted
    assert "sized for a GPU" in err if noted else True
    # the loop's note, printed by the command with its name
    assert lines[-1].endswith("only 3 of the run's 9 optimiser steps are at the full learning rate")
    assert len(lines) == 1 + noted
