"""The rows of panels every gallery draws, as PNG (:mod:`pfnet.viz.rendering`) or HTML
(:mod:`pfnet.viz.viewer`): a panel is a column title and the clouds drawn in it, and
:func:`column_titles` puts each panel of each row under its column."""

from __future__ import annotations

import numpy as np

__all__ = ["Layer", "Panel", "column_titles"]

Layer = tuple[np.ndarray, "str | np.ndarray"]
"""A cloud and its colour: ``"#rrggbb"``, or ``(N, 3)`` floats in ``[0, 1]``, one per point."""
Panel = tuple[str, list[Layer]]
"""A column title and the layers drawn in that panel, back to front."""


def column_titles(rows: list[tuple[str, list[Panel]]]) -> list[str]:
    """The columns of ``rows``: every panel title once, each row's titles in that row's order.

    A title that an earlier row lacks goes before the next of its row's titles already placed
    (after the previous one if none follows), so a row without a prediction does not move the
    ground truth under the prediction's column: rows ``[input, ground truth]`` then
    ``[input, completion, ground truth]`` give ``[input, completion, ground truth]``.
    """
    titles: list[str] = []
    for _, panels in rows:
        names = [name for name, _ in panels]
        for i, name in enumerate(names):
            if name in titles:
                continue
            after = [n for n in names[i + 1 :] if n in titles]
            before = [n for n in names[:i] if n in titles]
            if after:
                titles.insert(titles.index(after[0]), name)
            elif before:
                titles.insert(titles.index(before[-1]) + 1, name)
            else:
                titles.append(name)
    return titles
