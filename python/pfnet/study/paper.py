"""The paper's published numbers the study is compared with (Huang et al., CVPR 2020)."""

from __future__ import annotations

from pfnet.models.registry import PAPER_MODELS

# The paper's ranking, best first: the registry lists the models in that order (Table 4).
PAPER_ORDER = PAPER_MODELS

# The paper's figures (×1000) the tables are compared with (DESIGN.md §5).


PAPER_TABLE4_CHAIR = {
    "pfnet-vanilla": (1.772, 1.432),
    "mr-cmlp": (2.521, 2.275),
    "cmlp": (2.587, 2.306),
    "mlp": (2.692, 2.384),
}


# PF-Net's mean over the 13 categories: missing region (Table 2), whole cloud (Table 1).
PAPER_MEANS = {"missing": (2.426, 2.117), "whole": (0.555, 0.458)}


PAPER_TABLE2_CHAIR_MISSING = {"pfnet": (2.074, 1.824), "pfnet-vanilla": (1.998, 1.828)}


PAPER_TABLE5_AIRPLANE = {0.25: (0.727, 0.542), 0.5: (0.727, 0.520), 0.75: (0.748, 0.623)}
