"""The output type shared by every completion model."""

from __future__ import annotations

from typing import NamedTuple

from torch import Tensor


class Completion(NamedTuple):
    """A model's prediction of the missing region.

    Attributes:
        primary: ``(B, 64, 3)`` primary centres of the point pyramid decoder, or ``None``
            for models without one (the baselines).
        secondary: ``(B, 128, 3)`` secondary centres, or ``None``.
        detail: ``(B, M, 3)`` the predicted missing points.
    """

    primary: Tensor | None
    secondary: Tensor | None
    detail: Tensor
