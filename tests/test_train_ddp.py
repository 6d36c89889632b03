"""`pfnet train` under torchrun: DistributedDataParallel with 2 CPU processes (gloo)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from pfnet.checkpoint import load_checkpoint  # noqa: E402


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
