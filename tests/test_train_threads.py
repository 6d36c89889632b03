"""pfnet train's torch threads (issue 34 item 5): by default the cores other work leaves idle."""

from __future__ import annotations

from pathlib import Path

import pytest

from pfnet.cli import main
from pfnet.commands.train import torch_threads
from pfnet.processes import idle_cpus


@pytest.mark.parametrize(
    ("cpus", "load", "idle"), [(2, 0.1, 2), (2, 0.6, 1), (2, 3.2, 1), (16, 4.4, 12), (1, 0.0, 1)]
)
def test_idle_cpus_leaves_the_busy_cores_to_other_work(cpus, load, idle):
    assert idle_cpus(cpus, load) == idle


def test_auto_threads_follow_the_idle_cores_and_share_them_among_torchrun_processes(
    monkeypatch: pytest.MonkeyPatch,
):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.delenv("LOCAL_WORLD_SIZE", raising=False)
    monkeypatch.setattr("pfnet.processes.idle_cpus", lambda: 6)
    assert torch_threads("auto") == 6
    assert torch_threads(3) == 3
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "4")
    assert torch_threads("auto") == 1
    monkeypatch.setenv("OMP_NUM_THREADS", "2")  # the user's setting wins over auto
    assert torch_threads("auto") is None
    assert torch_threads(5) == 5


@pytest.mark.parametrize("bad", ["0", "-2", "two", "1.5"])
def test_a_bad_thread_count_is_refused_by_name(
    bad: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    argv = ["train", "--data", str(tmp_path), "--out", str(tmp_path / "r"), "--threads", bad]
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    assert f"--threads: must be auto or a positive whole number, got '{bad}'" in (
        capsys.readouterr().err
    )


def test_the_command_sets_the_threads_it_is_given(
    tiny_dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    torch = pytest.importorskip("torch")
    before = torch.get_num_threads()
    argv = ["train", "--data", str(tiny_dataset), "--out", str(tmp_path / "r"), "--preset"]
    argv += ["small", "--model", "mlp", "--epochs", "1", "--width", "0.125", "--device", "cpu"]
    try:
        assert main([*argv, "--threads", "1"]) == 0
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)
    capsys.readouterr()
