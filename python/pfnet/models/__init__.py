"""Completion models: PF-Net, PF-Net (vanilla), the MLP / CMLP / MR-CMLP baselines.

Every generator maps ``partial (B, n, 3)`` to a :class:`Completion` and carries
``n_points`` (complete cloud size it was trained for), ``n_missing`` (M, points it predicts),
``adversarial`` (trained with the :class:`Discriminator`), ``multi_resolution`` (takes the
IFPS ``scale_indices``) and ``multi_stage`` (also predicts the primary and secondary centres).
Importing this package imports torch.
"""

from __future__ import annotations

from typing import Protocol

from torch import nn

from pfnet.errors import ConfigError
from pfnet.models.baselines import CMLPCompletion, MLPCompletion, MRCMLPCompletion
from pfnet.models.completion import Completion
from pfnet.models.pfnet import (
    CMLP,
    Discriminator,
    MultiResolutionEncoder,
    PFNet,
    PFNetVanilla,
    PointPyramidDecoder,
)

MODELS: dict[str, type[nn.Module]] = {
    "pfnet": PFNet,
    "pfnet-vanilla": PFNetVanilla,
    "mlp": MLPCompletion,
    "cmlp": CMLPCompletion,
    "mr-cmlp": MRCMLPCompletion,
}


class ModelSpec(Protocol):
    """What :func:`build_model` reads from a configuration (e.g. ``TrainConfig``)."""

    model: str
    n_points: int | None
    n_missing: int
    width: float


def build_model(config: ModelSpec) -> nn.Module:
    """Build the generator named by ``config.model`` (in training mode, on the CPU).

    Raises:
        ConfigError: Unknown model name, or sizes the model cannot produce.
    """
    if config.model not in MODELS:
        raise ConfigError(f"unknown model {config.model!r}; choose one of {', '.join(MODELS)}")
    if config.n_points is None:
        raise ConfigError("n_points is not set (it is taken from the dataset when training)")
    return MODELS[config.model](
        n_points=config.n_points, n_missing=config.n_missing, width=config.width
    )


__all__ = [
    "CMLP",
    "MODELS",
    "CMLPCompletion",
    "Completion",
    "Discriminator",
    "MLPCompletion",
    "MRCMLPCompletion",
    "MultiResolutionEncoder",
    "PFNet",
    "PFNetVanilla",
    "PointPyramidDecoder",
    "build_model",
]
