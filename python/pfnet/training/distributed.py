"""DistributedDataParallel support: the same ``pfnet train`` under ``torchrun``.

``torchrun --nproc_per_node N -m pfnet.cli train ...`` sets ``RANK``, ``WORLD_SIZE``,
``LOCAL_RANK`` and the rendezvous variables; :func:`setup` then joins the process group
(gloo on the CPU, nccl on CUDA). Without them training runs in one process.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.distributed as dist

from pfnet.errors import ConfigError


@dataclass(frozen=True)
class DistContext:
    """Where this process sits in a (possibly single-process) run.

    Attributes:
        rank: Global rank (0 in a single process).
        world_size: Number of processes.
        local_rank: Rank on this machine (selects the GPU).
        device: The device this process trains on.
    """

    rank: int
    world_size: int
    local_rank: int
    device: torch.device

    @property
    def distributed(self) -> bool:
        """Whether a process group with more than one process is active."""
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        """Rank 0: the only process that writes files and shows progress."""
        return self.rank == 0


def resolve_device(
    device: str | torch.device,
    local_rank: int = 0,
    local_world_size: int = 1,
    say: Callable[[str], None] | None = None,
) -> torch.device:
    """The device of process ``local_rank`` of the ``local_world_size`` on this machine.

    ``auto`` takes ``cuda:<local_rank>`` when every local process can have a GPU of its own,
    else the CPU: a run that asked for nothing in particular should start, and all ranks
    must agree (they see the same counts). When some GPUs are visible but fewer than the
    processes, the CPU fallback is said to ``say`` (``pfnet train`` prints it on stderr).
    ``cuda`` means ``cuda:<local_rank>``.

    Raises:
        ConfigError: Unknown device string, CUDA requested but not available, or a GPU index
            beyond the visible ones (the message names both counts).
    """
    name = str(device)
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    if name == "auto":
        if count and count >= local_world_size:
            return torch.device(f"cuda:{local_rank}")
        if count and local_rank == 0 and say is not None:
            say(
                f"pfnet: {local_world_size} processes on this machine but {count} GPU(s) "
                f"visible: device auto trains on the CPU (start at most {count} processes "
                "per machine to use the GPUs)"
            )
        return torch.device("cpu")
    if name == "cpu":
        return torch.device("cpu")
    match = re.fullmatch(r"cuda(?::(\d+))?", name)
    if match is None:
        raise ConfigError(f"device must be auto, cpu, cuda or cuda:N; got {device!r}")
    if not count:
        raise ConfigError(f"device {device!r} requested but CUDA is not available")
    index = int(match.group(1)) if match.group(1) is not None else local_rank
    if index >= count:
        who = (
            f"process {local_rank} of {local_world_size} on this machine"
            if match.group(1) is None
            else "this process"
        )
        raise ConfigError(
            f"{who} needs GPU {index} but {count} GPU(s) are visible; "
            "start fewer processes per machine, or train on the CPU"
        )
    return torch.device(f"cuda:{index}")


def setup(
    device: str | torch.device = "auto", say: Callable[[str], None] | None = None
) -> DistContext:
    """Join the torchrun process group if there is one and pick this process's device (what
    :func:`resolve_device` has to say goes to ``say``)."""
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    local_world_size = int(os.environ.get("LOCAL_WORLD_SIZE", str(world_size)))
    resolved = resolve_device(device, local_rank, local_world_size, say)
    if world_size > 1 and not dist.is_initialized():
        if resolved.type == "cuda":
            torch.cuda.set_device(resolved)
        dist.init_process_group(backend="nccl" if resolved.type == "cuda" else "gloo")
    return DistContext(rank, world_size, local_rank, resolved)


def teardown(context: DistContext, *, finished: bool = True) -> None:
    """Leave the process group joined by :func:`setup`.

    ``destroy_process_group`` is meant to be called by all ranks together. After a run that
    ``finished`` (returned normally on this rank) every rank first waits at a barrier: rank
    0 still writes the last checkpoint, log and plot while the others are done, and a rank
    that tore down gloo and exited meanwhile was seen to abort (SIGABRT, "terminate called
    without an active exception") on a loaded machine. After an error on this rank there is
    no barrier: the other ranks may be waiting in a different collective and would never
    reach it; torchrun ends them once this process exits non-zero.
    """
    if context.distributed and dist.is_initialized():
        if finished:
            dist.barrier()
        dist.destroy_process_group()


def epoch_means(sums: dict[str, float], context: DistContext) -> dict[str, float]:
    """The mean over all processes of each running sum in ``sums`` (``count``: the samples
    they add up)."""
    keys = sorted(k for k in sums if k != "count")
    values = torch.tensor([sums[k] for k in keys] + [sums.get("count", 0.0)], dtype=torch.float64)
    if context.distributed:
        values = values.to(context.device)
        dist.all_reduce(values)
        values = values.cpu()
    count = float(values[-1]) or 1.0
    return {k: float(v) / count for k, v in zip(keys, values[:-1].tolist(), strict=True)}


def any_rank(flag: bool, context: DistContext) -> bool:
    """True on every rank if ``flag`` is true on any rank (e.g. a Ctrl-C seen by one)."""
    if not context.distributed:
        return flag
    value = torch.tensor([1.0 if flag else 0.0], device=context.device)
    dist.all_reduce(value, op=dist.ReduceOp.MAX)
    return bool(value.item() > 0)


def all_gather_objects(obj: object, context: DistContext) -> list[object]:
    """Every rank's ``obj``, in rank order (``[obj]`` in a single process)."""
    if not context.distributed:
        return [obj]
    gathered: list[object] = [None] * context.world_size
    dist.all_gather_object(gathered, obj)
    return gathered


def broadcast_object(obj: object, context: DistContext) -> object:
    """Rank 0's ``obj`` on every rank."""
    if not context.distributed:
        return obj
    box = [obj]
    dist.broadcast_object_list(box, src=0)
    return box[0]
