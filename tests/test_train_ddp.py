"""`pfnet train` under torchrun: DistributedDataParallel with 2 CPU processes (gloo)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from pfnet.inference.checkpoint import load_checkpoint  # noqa: E402


def _torchrun(*args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nnodes", "1"]
    command += ["--nproc-per-node", "2", "-m", "pfnet.cli", "train", *args]
    return subprocess.run(command, capture_output=True, text=True, env=env, timeout=300)


@pytest.mark.slow
def test_two_cpu_processes_train_with_ddp(tiny_dataset: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    args = ["--data", str(tiny_dataset), "--out", str(run), "--preset", "small", "--width", "0.125"]
    args += ["--epochs", "2", "--batch-size", "4", "--device", "cpu"]
    done = _torchrun(*args)
    assert done.returncode == 0, done.stderr[-3000:]
    # Only rank 0 reports and writes.
    assert done.stdout.count("trained pfnet for 2 epoch(s) on 2 process(es)") == 1
    rows = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in rows] == [0, 1, 2]
    assert all(r["val_cd_l2"] > 0 for r in rows)
    raw = torch.load(run / "last.pt", weights_only=True)
    assert raw["world_size"] == 2
    assert not any(k.startswith("module.") for k in raw["model"])  # unwrapped from DDP
    model, config = load_checkpoint(run / "last.pt")
    assert config.model == "pfnet" and not model.training
    assert sorted(p.name for p in run.iterdir()) == [
        "best.pt",
        "config.json",
        "curves.png",
        "last.pt",
        "log.jsonl",
    ]

    # Resuming a finished DDP run for one more epoch, again with 2 processes.
    done = _torchrun(
        "--data",
        str(tiny_dataset),
        "--out",
        str(run),
        "--resume",
        "--epochs",
        "3",
        "--device",
        "cpu",
    )
    assert done.returncode == 0, done.stderr[-3000:]
    rows = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in rows] == [0, 1, 2, 3]


class _RecordingDist:
    """Stands in for ``torch.distributed`` in the teardown tests: records the calls."""

    def __init__(self) -> None:
        self.calls: list[str] = []

    def is_initialized(self) -> bool:
        return True

    def barrier(self) -> None:
        self.calls.append("barrier")

    def destroy_process_group(self) -> None:
        self.calls.append("destroy")


@pytest.mark.parametrize(
    ("finished", "calls"), [(True, ["barrier", "destroy"]), (False, ["destroy"])]
)
def test_teardown_waits_for_every_rank_only_after_a_finished_run(
    monkeypatch: pytest.MonkeyPatch, finished: bool, calls: list[str]
) -> None:
    from pfnet.training import distributed

    fake = _RecordingDist()
    monkeypatch.setattr(distributed, "dist", fake)
    context = distributed.DistContext(1, 2, 1, torch.device("cpu"))
    distributed.teardown(context, finished=finished)
    assert fake.calls == calls
    # A single process has no group to leave.
    fake.calls.clear()
    distributed.teardown(distributed.DistContext(0, 1, 0, torch.device("cpu")))
    assert fake.calls == []


@pytest.mark.parametrize("fails", [False, True])
def test_train_tells_teardown_whether_the_run_finished(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, fails: bool
) -> None:
    from pfnet.training import distributed, loop

    seen: list[bool] = []

    class _Trainer:
        def __init__(self, *args: object, **kwargs: object) -> None:
            pass

        def run(self, progress: bool = False, **heard: object) -> dict[str, object]:
            if fails:
                raise RuntimeError("rank-local failure")
            return {"epochs": 1}

    monkeypatch.setattr(loop, "Trainer", _Trainer)
    monkeypatch.setattr(distributed, "teardown", lambda ctx, *, finished: seen.append(finished))
    config = loop.TrainConfig()
    if fails:
        with pytest.raises(RuntimeError, match="rank-local failure"):
            loop.train(config, tmp_path / "data", tmp_path / "run", device="cpu")
    else:
        assert loop.train(config, tmp_path / "data", tmp_path / "run", device="cpu") == {
            "epochs": 1
        }
    assert seen == [not fails]
