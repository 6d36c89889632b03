"""Building a generator from its configuration, and the authors' initialisation."""

from __future__ import annotations

from typing import TypeVar

from torch import nn

from pfnet.errors import ConfigError
from pfnet.models.completion import CompletionModel
from pfnet.models.config import INIT_SCHEMES, ModelConfig
from pfnet.models.registry import REGISTRY

Module = TypeVar("Module", bound=nn.Module)


def build_model(config: ModelConfig) -> CompletionModel:
    """Build the generator ``config`` describes (in training mode, on the CPU).

    Its weights start as PyTorch initialises each layer; :func:`initialise` applies another
    scheme.

    Raises:
        ConfigError: Unknown model name, or sizes the model cannot produce.
    """
    if config.model not in REGISTRY:
        raise ConfigError(f"unknown model {config.model!r}; choose one of {', '.join(REGISTRY)}")
    if config.n_points is None:
        raise ConfigError("n_points is not set (it is taken from the dataset when training)")
    model_class = REGISTRY[config.model].load()
    return model_class(n_points=config.n_points, n_missing=config.n_missing, width=config.width)


def initialise(module: Module, scheme: str) -> Module:
    """Re-initialise ``module``'s weights in place by ``scheme``; returns ``module``.

    ``pytorch`` keeps PyTorch's per-layer defaults (Kaiming-uniform weights, BatchNorm
    weight 1 and bias 0). ``authors`` is ``weights_init_normal`` of the authors'
    ``Train_PFNet.py``, which they apply to the generator and the discriminator alike:
    convolution weights N(0, 0.02) and BatchNorm weights N(1, 0.02) with biases 0.
    Convolution biases and fully connected layers keep PyTorch's defaults, as theirs do.
    Draws from torch's global generator: seed it first for a reproducible start.

    Raises:
        ConfigError: An unknown scheme.
    """
    if scheme not in INIT_SCHEMES:
        raise ConfigError(f"init must be one of {', '.join(INIT_SCHEMES)}; got {scheme!r}")
    if scheme == "authors":
        for layer in module.modules():
            if isinstance(layer, nn.Conv1d | nn.Conv2d):
                nn.init.normal_(layer.weight, 0.0, 0.02)
            elif isinstance(layer, nn.BatchNorm1d | nn.BatchNorm2d):  # BatchNormFC too
                nn.init.normal_(layer.weight, 1.0, 0.02)
                nn.init.zeros_(layer.bias)
    return module
