"""What every completion model returns (:class:`Completion`) and declares (its base class)."""

from __future__ import annotations

from typing import ClassVar, NamedTuple

from torch import Tensor, nn


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


class CompletionModel(nn.Module):
    """The base of every generator: ``forward(partial, scale_indices=None) -> Completion``.

    Each subclass declares its capabilities, which the training loop reads to build batches
    and losses.

    Attributes:
        adversarial: Trained against a :class:`pfnet.models.Discriminator` (Eq. 4).
        multi_resolution: Its encoder reads the IFPS ``scale_indices`` of the partial cloud
            (computed in data-loader workers when training).
        multi_stage: Also predicts the primary and secondary centres (Eq. 2's extra terms).
        n_points: Size N of the complete clouds the model is trained for.
        n_missing: M, the number of points it predicts.
    """

    adversarial: ClassVar[bool]
    multi_resolution: ClassVar[bool]
    multi_stage: ClassVar[bool]
    n_points: int
    n_missing: int

    def forward(self, partial: Tensor, scale_indices: Tensor | None = None) -> Completion:
        """Predict the missing region of ``(B, n, 3)`` partial clouds."""
        raise NotImplementedError
