"""Device choice (``--device``), under torchrun too, with the GPU count faked."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from pfnet.errors import ConfigError  # noqa: E402
from pfnet.training.distributed import resolve_device  # noqa: E402


@pytest.fixture
def gpus(monkeypatch: pytest.MonkeyPatch):
    def set_count(count: int) -> None:
        monkeypatch.setattr(torch.cuda, "is_available", lambda: count > 0)
        monkeypatch.setattr(torch.cuda, "device_count", lambda: count)

    return set_count


def test_auto_gives_every_local_process_its_own_gpu(gpus) -> None:
    gpus(2)
    assert resolve_device("auto", 0, 2) == torch.device("cuda:0")
    assert resolve_device("auto", 1, 2) == torch.device("cuda:1")
    assert resolve_device("cuda", 1, 2) == torch.device("cuda:1")
    assert resolve_device("cuda:0", 1, 2) == torch.device("cuda:0")


def test_auto_falls_back_to_the_cpu_when_gpus_are_fewer_than_processes(gpus, capsys) -> None:
    gpus(1)
    said: list[str] = []
    assert resolve_device("auto", 0, 2, said.append) == torch.device("cpu")
    assert "2 processes on this machine but 1 GPU(s) visible" in said.pop()
    assert resolve_device("auto", 1, 2, said.append) == torch.device("cpu")
    assert not said  # said once, by local rank 0
    gpus(0)
    assert resolve_device("auto", 0, 1, said.append) == torch.device("cpu")
    assert not said
    assert resolve_device("auto", 0, 2) == torch.device("cpu")  # the library prints nothing
    assert capsys.readouterr().err == ""


def test_explicit_gpus_beyond_the_visible_ones_are_refused_with_the_counts(gpus) -> None:
    gpus(1)
    with pytest.raises(ConfigError, match="process 1 of 2 on this machine needs GPU 1 but 1 GPU"):
        resolve_device("cuda", 1, 2)
    with pytest.raises(ConfigError, match="needs GPU 3 but 1 GPU"):
        resolve_device("cuda:3")
    gpus(0)
    with pytest.raises(ConfigError, match="'cuda:0' requested but CUDA is not available"):
        resolve_device("cuda:0")
    for bad in ("tpu", "cuda:x", "cuda:-1", "CPU"):
        with pytest.raises(ConfigError, match="device must be auto, cpu, cuda or cuda:N"):
            resolve_device(bad)
