"""The crop protocol (DESIGN.md §3): how many points go missing, and the deterministic test crop.

The authors remove the ``M`` points nearest a viewpoint chosen at random among five. For
reproducible scores the test protocol fixes the choice: test sample ``i`` (in dataset order)
uses ``VIEWPOINTS[i % 5]``. Training validation, ``pfnet predict`` and ``pfnet evaluate``
all crop with :func:`test_protocol_crop`.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from pfnet.errors import ConfigError

if TYPE_CHECKING:
    from pfnet.data.format import CloudSet

__all__ = ["VIEWS", "every_view", "missing_count", "test_protocol_crop", "test_protocol_viewpoints"]

VIEWS: tuple[int, ...] = (1, 5)
"""How many of the five viewpoints the test protocol may cut each shape at: one (sample ``i``
at ``VIEWPOINTS[i % 5]``, the paper's) or all five (:func:`every_view`)."""


def missing_count(n_points: int, missing_ratio: float) -> int:
    """Points removed from a cloud of ``n_points``: ``round(missing_ratio · n_points)``.

    Python's ``round`` (halves to even); 512 of 2048 at the paper's 25 %.

    Args:
        n_points: Points per complete cloud.
        missing_ratio: Share removed, ``0 < missing_ratio < 1``.

    Returns:
        ``m`` with ``1 <= m <= n_points - 1``.

    Raises:
        ConfigError: The ratio is out of range or leaves nothing to remove or to keep.
    """
    if not (isinstance(missing_ratio, (int, float)) and math.isfinite(missing_ratio)):
        raise ConfigError(f"missing_ratio must be a number in (0, 1), got {missing_ratio!r}")
    if not 0 < missing_ratio < 1:
        raise ConfigError(f"missing_ratio must be in (0, 1), got {missing_ratio}")
    m = round(missing_ratio * n_points)
    if not 1 <= m <= n_points - 1:
        raise ConfigError(
            f"missing_ratio {missing_ratio} removes {m} of {n_points} points; "
            "it must remove at least one and keep at least one"
        )
    return m


def test_protocol_viewpoints(n_samples: int) -> np.ndarray:
    """The viewpoint of each test sample: ``VIEWPOINTS[i % 5]``, float32 ``(n_samples, 3)``."""
    from pfnet.geometry import VIEWPOINTS

    return VIEWPOINTS[np.arange(n_samples) % len(VIEWPOINTS)]


def test_protocol_crop(points: np.ndarray, missing_ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Crop a split with the deterministic test protocol.

    Sample ``i`` loses the ``m = round(r·N)`` points nearest ``VIEWPOINTS[i % 5]``; both
    outputs keep the points' original order.

    Args:
        points: ``(S, N, 3)`` complete clouds, in dataset order.
        missing_ratio: ``r``, e.g. 0.25 (paper), 0.5 or 0.75 (robustness study).

    Returns:
        ``(partial, missing)``: ``(S, N - m, 3)`` and ``(S, m, 3)``, in the input dtype.
    """
    from pfnet.geometry import crop_by_viewpoint

    points = np.asarray(points)
    if points.ndim != 3 or points.shape[2] != 3:
        raise ConfigError(f"points must have shape (S, N, 3), got {points.shape}")
    n_samples, n_points = points.shape[:2]
    m = missing_count(n_points, missing_ratio)
    if n_samples == 0:
        return points[:, : n_points - m], points[:, :m]
    return crop_by_viewpoint(points, test_protocol_viewpoints(n_samples), n_missing=m)


# Not tests: keep pytest from collecting these where a test module imports them by name.
test_protocol_crop.__test__ = False  # type: ignore[attr-defined]
test_protocol_viewpoints.__test__ = False  # type: ignore[attr-defined]


def every_view(clouds: CloudSet, views: int) -> CloudSet:
    """``clouds`` with each shape ``views`` times in a row (one of :data:`VIEWS`), named
    ``NAME-vV``, so that the test protocol's ``VIEWPOINTS[j % 5]`` (and the scanner's test
    camera ``j``) cut shape ``i`` at all five viewpoints, as samples ``5 i`` to ``5 i + 4``.

    One cut per shape leaves a mean to the few cuts that go wrong; five give every shape the
    same weight at every viewpoint. ``views = 1`` returns ``clouds`` itself. A pool of
    points (``extra``) is dropped: the test protocols use the stored clouds.

    Raises:
        ConfigError: ``views`` is not one of :data:`VIEWS`.
    """
    from pfnet.data.format import CloudSet

    if isinstance(views, bool) or views not in VIEWS:
        raise ConfigError(f"views must be 1 or 5 (of the five viewpoints), got {views!r}")
    if views == 1:
        return clouds
    names = [f"{name}-v{v}" for name in clouds.name.tolist() for v in range(views)]
    return CloudSet(
        np.repeat(np.asarray(clouds.points, np.float32), views, axis=0),
        np.repeat(clouds.category, views),
        np.array(names, dtype=str),  # str even for an empty split
    )
