"""An exponential moving average of the generator's weights (``ema`` in the configuration).

Not in the paper: a lever for small data sets, where the validation error of the live
weights jumps from epoch to epoch (README, Training). The average is what validation scores,
``best.pt`` holds and inference runs; the optimiser keeps training the live weights.
"""

from __future__ import annotations

import copy
from typing import Any

import torch
from torch import nn


class WeightAverage:
    """``average ← d·average + (1 − d)·weights`` after every optimiser step.

    The decay ramps up as ``d = min(decay, (1 + n) / (10 + n))`` over the first ``n`` updates,
    so the average forgets the initial weights within a few dozen steps instead of ``1 / (1 -
    decay)``. BatchNorm running statistics are averaged the same way; integer buffers (the
    batch counters) are copied.

    Args:
        model: The live network; the average starts as a copy of it, in eval mode.
        decay: Weight of the old average per update, in ``(0, 1)``.
    """

    def __init__(self, model: nn.Module, decay: float) -> None:
        if not 0 < decay < 1:
            raise ValueError(f"decay must be in (0, 1), got {decay!r}")
        self.decay = decay
        self.model = copy.deepcopy(model).eval()
        self.model.requires_grad_(False)
        self.updates = 0

    def decay_at(self, updates: int) -> float:
        """The decay of update number ``updates`` (1 for the first)."""
        return min(self.decay, (1 + updates) / (10 + updates))

    @torch.no_grad()
    def reset(self, model: nn.Module) -> None:
        """Start the average again from ``model``'s weights (after loading other weights)."""
        self.model.load_state_dict(model.state_dict())
        self.updates = 0

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        """Fold ``model``'s current weights into the average."""
        self.updates += 1
        keep = self.decay_at(self.updates)
        live = model.state_dict()
        for name, value in self.model.state_dict().items():
            if value.is_floating_point():
                value.lerp_(live[name], 1.0 - keep)
            else:
                value.copy_(live[name])

    def state_dict(self) -> dict[str, Any]:
        """The averaged weights and the number of updates."""
        return {"model": self.model.state_dict(), "updates": self.updates}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`state_dict` returned."""
        self.model.load_state_dict(state["model"])
        self.updates = int(state["updates"])
