"""Training: typed configuration, the training loop, DDP support and the ``train`` command.

``pfnet.training.train`` (the loop) imports torch when first used; the configuration does not.
"""

from __future__ import annotations

from typing import Any

from pfnet.training.config import PRESETS, TrainConfig, load_config, preset_config

__all__ = ["PRESETS", "TrainConfig", "load_config", "preset_config", "train"]


def __getattr__(name: str) -> Any:
    if name == "train":
        from pfnet.training.loop import train

        return train
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
