"""Completion models: PF-Net, PF-Net (vanilla), the MLP / CMLP / MR-CMLP baselines, and
PF-Net + mirror (not the paper's: PF-Net reading the partial's mirror images).

Every generator is a :class:`CompletionModel`: it maps ``partial (B, n, 3)`` to a
:class:`Completion`, carries ``n_points`` (complete cloud size it was trained for) and
``n_missing`` (M, points it predicts), and declares ``adversarial`` (trained with the
:class:`Discriminator`), ``multi_resolution`` (takes the IFPS ``scale_indices``) and
``multi_stage`` (also predicts the primary and secondary centres). :data:`REGISTRY` is the one
list of them; :class:`ModelConfig` says which one, at what size.

Importing this package needs no torch; the network classes and :func:`build_model` import it
when first used.
"""

from __future__ import annotations

import importlib
from typing import Any

from pfnet.models.config import INIT_SCHEMES, ModelConfig
from pfnet.models.registry import (
    MODEL_NAMES,
    MODEL_TITLES,
    PAPER_MODELS,
    REGISTRY,
    RegisteredModel,
)

# Names importable from here that need torch: imported on first access.
_LAZY = {
    "CMLP": "pfnet.models.pfnet",
    "MultiResolutionEncoder": "pfnet.models.pfnet",
    "PointPyramidDecoder": "pfnet.models.pfnet",
    "Discriminator": "pfnet.models.pfnet",
    "PFNet": "pfnet.models.pfnet",
    "PFNetVanilla": "pfnet.models.pfnet",
    "PFNetMirror": "pfnet.models.mirror",
    "PFNetEdge": "pfnet.models.edge",
    "MLPCompletion": "pfnet.models.baselines",
    "CMLPCompletion": "pfnet.models.baselines",
    "MRCMLPCompletion": "pfnet.models.baselines",
    "Completion": "pfnet.models.completion",
    "CompletionModel": "pfnet.models.completion",
    "build_model": "pfnet.models.build",
    "initialise": "pfnet.models.build",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    if name == "MODELS":  # name -> class, read from the registry
        return {model: entry.load() for model, entry in REGISTRY.items()}
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "CMLP",
    "INIT_SCHEMES",
    "MODELS",
    "MODEL_NAMES",
    "MODEL_TITLES",
    "PAPER_MODELS",
    "REGISTRY",
    "CMLPCompletion",
    "Completion",
    "CompletionModel",
    "Discriminator",
    "MLPCompletion",
    "MRCMLPCompletion",
    "ModelConfig",
    "MultiResolutionEncoder",
    "PFNet",
    "PFNetEdge",
    "PFNetMirror",
    "PFNetVanilla",
    "PointPyramidDecoder",
    "RegisteredModel",
    "build_model",
    "initialise",
]
