"""The paper's colours (Figs. 7-9), which every picture pfnet draws and every coloured cloud it
writes uses: the input grey, the predicted missing region yellow, the ground truth blue."""

from __future__ import annotations

__all__ = ["GROUND_TRUTH_COLOR", "PARTIAL_COLOR", "PREDICTION_COLOR", "rgb"]

PARTIAL_COLOR = "#9a9a9a"
"""Grey: the incomplete input (paper, Figs. 7-9)."""
PREDICTION_COLOR = "#f2c200"
"""Yellow: the predicted missing region."""
GROUND_TRUTH_COLOR = "#2f6fd0"
"""Blue: the complete ground-truth cloud."""


def rgb(color: str) -> tuple[int, int, int]:
    """``"#rrggbb"`` as an ``(r, g, b)`` tuple of 0-255 integers."""
    return (int(color[1:3], 16), int(color[3:5], 16), int(color[5:7], 16))
