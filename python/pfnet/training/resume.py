"""What ``--resume`` checks: the same data set, and a configuration changed only where allowed."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

from pfnet.errors import ConfigError
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
