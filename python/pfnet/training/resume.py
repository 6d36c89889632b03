"""What ``--resume`` checks: the same data set, and a configuration changed only where allowed."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import torch

from pfnet.errors import ConfigError, DataError
from pfnet.training.config import RESUMABLE_FIELDS, TrainConfig


def data_identity(data_dir: Path) -> dict[str, str]:
    """What a run records of its data set, so that ``--resume`` can refuse another one.

    The fingerprint covers the manifest (source, options, seed, every shape's name and split)
    and the split files' sizes; a data set moved or copied elsewhere keeps it.
    """
    digest = hashlib.sha256()
    manifest = Path(data_dir) / "manifest.json"
    if manifest.is_file():
        digest.update(manifest.read_bytes())
    for split in ("train", "val"):
        path = Path(data_dir) / f"{split}.npz"
        digest.update(f"{split}:{path.stat().st_size if path.is_file() else -1};".encode())
    return {"path": str(Path(data_dir).resolve()), "fingerprint": digest.hexdigest()}


def resumed_config(config: TrainConfig, state: dict[str, Any], path: Path) -> TrainConfig:
    """The stored config with the resumable fields of ``config``; refuse other changes."""
    stored = TrainConfig.from_dict(state["config"], source=f"checkpoint {path}")
    requested = config.to_dict()
    for key, value in stored.to_dict().items():
        if key in RESUMABLE_FIELDS or (key == "n_points" and requested[key] is None):
            continue
        if requested[key] != value:
            raise ConfigError(
                f"cannot change {key} when resuming: {path} was trained with {value!r}, "
                f"got {requested[key]!r}"
            )
    return stored.replace(**{k: requested[k] for k in RESUMABLE_FIELDS})


# More epochs than any run trains: a larger stored counter is a damaged or forged file.
MAX_EPOCHS = 1_000_000


def check_resumable(state: dict[str, Any], path: Path) -> None:
    """Refuse a ``last.pt`` that is not a whole, finite training state.

    A plain model checkpoint copied over ``last.pt`` (a ``KeyError`` traceback before), NaN
    weights (a run that would train on NaN to the end with exit 0) and forged counters are
    named in one line.

    Raises:
        DataError: What is missing or wrong, naming ``path``.
    """
    needed = ("optimizer_g", "scheduler_g", "epoch", "batches_done", "epoch_sums", "history")
    missing = [key for key in (*needed, "best_metric", "rng", "world_size") if key not in state]
    if missing:
        raise DataError(
            f"{path} is not a training state to resume (no {', '.join(missing)}): "
            "a model file, or damaged"
        )
    for key in ("epoch", "batches_done", "world_size"):
        value = state[key]
        if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value <= MAX_EPOCHS:
            raise DataError(f"{path} has an impossible {key} ({value!r}): damaged or forged")
    for part in ("model", "discriminator"):
        weights = state.get(part) or {}
        broken = [
            name
            for name, value in weights.items()
            if isinstance(value, torch.Tensor) and not value.isfinite().all()
        ]
        if broken:
            raise DataError(
                f"{path} holds NaN or infinite {part} weights (e.g. {broken[0]}): the run "
                "diverged; start again from an earlier checkpoint"
            )
