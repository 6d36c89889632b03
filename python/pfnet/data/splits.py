"""Train/val/test splits of a source that has none: per category, by seed."""

from __future__ import annotations

from collections.abc import Sequence

from pfnet.data.sampling import shape_rng
from pfnet.data.sources import ShapeItem


def assign_splits(
    items: Sequence[ShapeItem], seed: int, test_fraction: float, val_fraction: float
) -> list[str]:
    """Split each category by seed: ``round(f·n)`` test and val shapes, at least one train shape.

    The permutation of a category depends only on the seed, the category and its keys.

    Args:
        items: The shapes.
        seed: The dataset seed.
        test_fraction: Fraction of each category for ``test``.
        val_fraction: Fraction of each category for ``val``.

    Returns:
        The split of each item, in order.
    """
    by_category: dict[str, list[int]] = {}
    for index, item in enumerate(items):
        by_category.setdefault(item.category, []).append(index)
    splits = ["train"] * len(items)
    for category, indices in by_category.items():
        indices = sorted(indices, key=lambda i: items[i].key)
        n = len(indices)
        n_test = min(round(test_fraction * n), n - 1)
        n_val = max(min(round(val_fraction * n), n - 1 - n_test), 0)
        order = shape_rng(seed, f"split:{category}").permutation(n)
        for rank, position in enumerate(order):
            if rank < n_test:
                splits[indices[position]] = "test"
            elif rank < n_test + n_val:
                splits[indices[position]] = "val"
    return splits
