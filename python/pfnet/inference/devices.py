"""Where inference runs: one resolver for ``predict``, ``complete``, ``demo`` and ``reproduce``.

(Training resolves its device in :mod:`pfnet.training.distributed`, which also has to agree
with the other processes of a ``torchrun`` job.)
"""

from __future__ import annotations

import re

from pfnet.errors import ConfigError

DEVICE_HELP = "auto (CUDA if available), cpu, cuda or cuda:N (default: auto)"


def inference_device(name: str) -> str:
    """``auto`` → ``cuda`` if a GPU is visible, else ``cpu``; ``cpu``, ``cuda``, ``cuda:N``.

    Raises:
        ConfigError: Another name, or a CUDA device that is not there (naming the count).
    """
    import torch

    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cpu":
        return name
    match = re.fullmatch(r"cuda(?::(\d+))?", name)
    if match is None:
        raise ConfigError(f"device must be auto, cpu, cuda or cuda:N, got {name!r}")
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    index = int(match.group(1) or 0)
    if index >= count:
        raise ConfigError(
            f"device {name}: this machine has {count} CUDA device(s) (use cpu or auto)"
        )
    return name
