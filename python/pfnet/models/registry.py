"""The one list of completion models: names, titles, and where each class lives.

Training's ``--model`` choices, configuration checks, the results study and
:func:`pfnet.models.build_model` all read :data:`REGISTRY`. The classes are imported when first
asked for, so the list needs no torch (the ``train`` parser and config errors stay cheap).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from pfnet.models.completion import CompletionModel


@dataclass(frozen=True)
class RegisteredModel:
    """One generator of the registry.

    Attributes:
        name: The name configurations and the command line use (``pfnet-vanilla``).
        title: How the paper's tables name it (``PF-Net (vanilla)``).
        module: The module defining its class.
        class_name: The class, a :class:`pfnet.models.CompletionModel`.
        paper: One of the paper's five networks (its tables and the study compare these).
    """

    name: str
    title: str
    module: str
    class_name: str
    paper: bool = True

    def load(self) -> type[CompletionModel]:
        """The generator class (imports torch)."""
        return getattr(importlib.import_module(self.module), self.class_name)


# The paper's order (Table 4, best first); the study's tables and curves follow it.
REGISTRY: dict[str, RegisteredModel] = {
    entry.name: entry
    for entry in (
        RegisteredModel("pfnet", "PF-Net", "pfnet.models.pfnet", "PFNet"),
        RegisteredModel("pfnet-vanilla", "PF-Net (vanilla)", "pfnet.models.pfnet", "PFNetVanilla"),
        # not the paper's: PF-Net (vanilla) reading the partial's mirror images (issue 34)
        RegisteredModel(
            "pfnet-mirror", "PF-Net + mirror", "pfnet.models.mirror", "PFNetMirror", paper=False
        ),
        # not the paper's: PF-Net + mirror also reading each point's edge score (issue 34)
        RegisteredModel(
            "pfnet-edge", "PF-Net + mirror + edge", "pfnet.models.edge", "PFNetEdge", paper=False
        ),
        RegisteredModel("mr-cmlp", "MR-CMLP", "pfnet.models.baselines", "MRCMLPCompletion"),
        RegisteredModel("cmlp", "CMLP", "pfnet.models.baselines", "CMLPCompletion"),
        RegisteredModel("mlp", "MLP", "pfnet.models.baselines", "MLPCompletion"),
    )
}

MODEL_NAMES: tuple[str, ...] = tuple(REGISTRY)
PAPER_MODELS: tuple[str, ...] = tuple(name for name, entry in REGISTRY.items() if entry.paper)
"""The paper's five networks, best first: what the study and its tables compare."""
MODEL_TITLES: dict[str, str] = {name: entry.title for name, entry in REGISTRY.items()}
