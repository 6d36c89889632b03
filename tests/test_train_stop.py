"""Stopping a training run is always safe: Ctrl-C at any moment saves a loadable ``last.pt``
(or leaves the previous one intact), exits with 130 without a traceback, and ``--resume``
continues to the same weights as an uninterrupted run."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from process_tree import fork_servers, wait_for

torch = pytest.importorskip("torch")

import pfnet.inference.checkpoint  # noqa: E402
from pfnet.inference.checkpoint import load_checkpoint, read_checkpoint  # noqa: E402
from pfnet.processes import spawn_shielded, start_helpers  # noqa: E402
from pfnet.training import preset_config, train  # noqa: E402
from pfnet.training.loop import Trainer  # noqa: E402
from pfnet.training.signals import StopRequest  # noqa: E402
from pfnet.training.step import TrainingStep  # noqa: E402

# Ctrl-C as in a terminal, even when the test suite runs in the background (SIGINT ignored)
pytestmark = pytest.mark.usefixtures("sigint_as_in_a_terminal")

# 24 training shapes in batches of 6: 4 steps an epoch.
CONFIG = preset_config("small").replace(epochs=2, batch_size=6, width=0.125, save_every="1")


@pytest.fixture(scope="module")
def uninterrupted(tiny_dataset: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    run = tmp_path_factory.mktemp("whole") / "run"
    train(CONFIG, tiny_dataset, run, device="cpu", progress=False)
    return run


def _sigint_on_call(monkeypatch: pytest.MonkeyPatch, owner: object, name: str, call: int) -> None:
    """Raise a real SIGINT at the start of the ``call``-th call of ``owner.name``."""
    original = getattr(owner, name)
    calls: list[int] = []

    def wrapper(*args, **kwargs):
        calls.append(1)
        if len(calls) == call:
            signal.raise_signal(signal.SIGINT)
            time.sleep(0.05)  # let the handler run while the call is under way
        return original(*args, **kwargs)

    monkeypatch.setattr(owner, name, wrapper)


MOMENTS = {
    # mid-batch: during the 6th training step (epoch 2, batch 2)
    "mid-batch": (TrainingStep, "__call__", 6),
    # at an epoch boundary: between epoch 1's last batch and its validation
    "epoch-boundary": (TrainingStep, "end_epoch", 1),
    # during validation of epoch 1 (call 1 is the untrained model's epoch 0)
    "validation": (Trainer, "validate", 2),
    # during a checkpoint write (the first one: best.pt after epoch 1, on the writer thread)
    "checkpoint-write": (pfnet.inference.checkpoint, "save_checkpoint", 1),
}


@pytest.mark.parametrize("moment", list(MOMENTS))
def test_ctrl_c_at_any_moment_saves_and_resumes_exactly(
    moment: str,
    tiny_dataset: Path,
    uninterrupted: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    run = tmp_path / "run"
    before = signal.getsignal(signal.SIGINT)
    with monkeypatch.context() as patch:
        _sigint_on_call(patch, *MOMENTS[moment])
        summary = train(CONFIG, tiny_dataset, run, device="cpu", progress=False)
    assert summary["interrupted"]
    assert signal.getsignal(signal.SIGINT) is before  # the handler is restored
    state = read_checkpoint(run / "last.pt")
    model, _ = load_checkpoint(run / "last.pt")
    assert (state["epoch"], state["batches_done"]) == (summary["epochs"], summary["batches_done"])
    assert not [p for p in run.iterdir() if p.name.startswith(".")]  # no temporary files

    resumed = train(CONFIG, tiny_dataset, run, device="cpu", progress=False, resume=True)
    assert not resumed["interrupted"] and resumed["epochs"] == 2
    a, b = read_checkpoint(uninterrupted / "last.pt"), read_checkpoint(run / "last.pt")
    for key in ("model", "discriminator"):
        for name, tensor in a[key].items():
            assert torch.equal(tensor, b[key][name]), f"{moment}: {key}.{name}"


def _blocked_and_ignored(pid: int) -> int:
    """The signals process ``pid`` blocks or ignores, as a bit mask (bit n-1: signal n)."""
    fields = dict(
        line.split(":\t", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines()
    )
    return int(fields["SigBlk"], 16) | int(fields["SigIgn"], 16)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_helpers_hold_the_stop_signals_from_their_first_instruction() -> None:
    code = "import time; time.sleep(60)"
    pid = spawn_shielded(sys.executable, [sys.executable, "-c", code], [])
    try:
        mask = _blocked_and_ignored(pid)  # before the interpreter has run a line of Python
        for signum in (signal.SIGINT, signal.SIGTERM):
            assert mask & (1 << (signum - 1)), signal.Signals(signum).name
        os.kill(pid, signal.SIGINT)
        time.sleep(0.2)
        assert os.waitpid(pid, os.WNOHANG) == (0, 0)  # still alive
    finally:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)


def test_passed_descriptors_reach_the_helper_and_stay_private_here() -> None:
    read, write = os.pipe()
    code = f"import os; os.write({write}, b'hello')"
    pid = spawn_shielded(sys.executable, [sys.executable, "-c", code], [write])
    try:
        assert not os.get_inheritable(write)
        assert os.waitpid(pid, 0)[1] == 0
        assert os.read(read, 5) == b"hello"
    finally:
        os.close(read), os.close(write)


def test_an_ignored_sigint_stays_ignored() -> None:
    """A run started in the background by a script (SIGINT ignored, as the shell leaves it)
    is not stopped by a Ctrl-C meant for the foreground; SIGTERM still stops it."""
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with StopRequest().installed() as stop:
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
            signal.raise_signal(signal.SIGINT)
            assert not stop.requested
            signal.raise_signal(signal.SIGTERM)
            assert stop.requested
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)


def test_a_stop_signal_while_the_helpers_start_reaches_the_training_process(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The old code ignored SIGINT here for the spawn, and a Ctrl-C in that moment was lost."""
    from multiprocessing import forkserver

    monkeypatch.setattr(forkserver, "ensure_running", lambda: signal.raise_signal(signal.SIGINT))
    with StopRequest().installed() as stop:
        start_helpers(["pfnet.training.loop"])
        assert stop.requested


def _start_run(tiny_dataset: Path, run: Path, *extra: str) -> subprocess.Popen[str]:
    command = [sys.executable, "-m", "pfnet.cli", "train", "--data", str(tiny_dataset)]
    command += ["--out", str(run), "--device", "cpu", *extra]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    # A session of its own: killpg reaches the run and all its helpers, as a terminal would.
    return subprocess.Popen(
        command, env=env, stderr=subprocess.PIPE, text=True, start_new_session=True
    )


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("when", ["workers-starting", "training"])
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_signal_to_the_process_group_exits_130_without_traceback(
    when: str, signum: int, tiny_dataset: Path, tmp_path: Path
) -> None:
    run = tmp_path / "run"
    options = ["--preset", "small", "--width", "0.125", "--batch-size", "4", "--epochs", "50"]
    process = _start_run(tiny_dataset, run, *options, "--workers", "2")
    try:
        if when == "workers-starting":
            # The fork server appears and spends seconds importing torch: the old moment of
            # a BrokenPipeError.
            wait_for(lambda: process.poll() is not None or fork_servers(process.pid))
        else:
            wait_for(lambda: process.poll() is not None or (run / "log.jsonl").exists())
            wait_for(lambda: len((run / "log.jsonl").read_text().splitlines()) >= 2)
        os.killpg(process.pid, signum)
        _, stderr = process.communicate(timeout=180)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
    assert process.returncode == 130, stderr[-3000:]
    assert "Traceback" not in stderr and "Error" not in stderr, stderr[-3000:]
    assert "continue with --resume" in stderr
    assert read_checkpoint(run / "last.pt")["config"]["workers"] == 2
    resumed = _start_run(tiny_dataset, run, "--resume", "--epochs", "2", "--workers", "1")
    _, stderr = resumed.communicate(timeout=180)
    assert resumed.returncode == 0, stderr[-3000:]
