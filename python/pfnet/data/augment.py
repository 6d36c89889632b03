"""Random augmentation of training clouds for small data sets (off in the paper's setup).

Applied to the complete cloud before the crop, so the partial input and the missing region
stay two parts of one shape. Every draw comes from a generator seeded by
``(seed, epoch, index)``, so augmented runs are reproducible with any number of workers.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pfnet.data.format import read_manifest
from pfnet.data.scan_frame import up_rotation
from pfnet.errors import ConfigError

__all__ = ["AXES", "Augmentation", "up_axis_index"]

AXES = ("x", "y", "z")


def up_axis_index(manifest: dict) -> int:
    """The index (0, 1, 2) of a data set's up axis, from its manifest's ``up_axis``.

    Raises:
        ConfigError: The manifest does not name the axis (e.g. a mesh folder whose
            orientation pfnet cannot know).
    """
    axis = manifest.get("up_axis")
    if axis not in AXES:
        raise ConfigError(
            f"rotation about the up axis needs a data set whose manifest names it (x, y or z); "
            f"this one says {axis!r}"
        )
    return AXES.index(axis)


@dataclass(frozen=True)
class Augmentation:
    """Random rotation about the up axis, anisotropic scaling and jitter.

    Attributes:
        up_axis: Index of the axis to rotate about (uniform angle), or ``None`` for none.
        scale: Each axis is multiplied by a factor drawn uniformly from
            ``[1 - scale, 1 + scale]`` (0: none).
        jitter: Standard deviation of Gaussian noise added to every coordinate, clipped at
            3 standard deviations (0: none).
    """

    up_axis: int | None = None
    scale: float = 0.0
    jitter: float = 0.0

    def __post_init__(self) -> None:
        if self.up_axis not in (None, 0, 1, 2):
            raise ConfigError(f"up_axis must be 0, 1, 2 or None, got {self.up_axis!r}")
        if not (np.isfinite(self.scale) and 0 <= self.scale < 1):
            raise ConfigError(f"scale must be in [0, 1), got {self.scale!r}")
        if not (np.isfinite(self.jitter) and 0 <= self.jitter <= 0.1):
            raise ConfigError(f"jitter must be in [0, 0.1], got {self.jitter!r}")

    @property
    def active(self) -> bool:
        """Whether it changes anything."""
        return self.up_axis is not None or self.scale > 0 or self.jitter > 0

    def __call__(self, points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """``points`` ``(N, 3)`` augmented, float32 (a new array)."""
        out = np.asarray(points, dtype=np.float64)
        if self.up_axis is not None:
            out = out @ up_rotation(rng.uniform(0.0, 2.0 * np.pi), self.up_axis).T
        if self.scale > 0:
            out = out * rng.uniform(1.0 - self.scale, 1.0 + self.scale, size=3)
        if self.jitter > 0:
            noise = rng.normal(0.0, self.jitter, size=out.shape)
            out = out + np.clip(noise, -3 * self.jitter, 3 * self.jitter)
        return out.astype(np.float32)


def augmentation_for(config: Any, data_dir: Path) -> Augmentation | None:
    """The training augmentation a ``TrainConfig`` asks for (``None`` when it asks for none)."""
    if not (config.augment_rotate or config.augment_scale or config.augment_jitter):
        return None
    up_axis = None
    if config.augment_rotate:
        try:
            up_axis = up_axis_index(read_manifest(data_dir))
        except ConfigError as err:
            raise ConfigError(f"augment_rotate: {err} ({data_dir})") from None
    return Augmentation(up_axis, config.augment_scale, config.augment_jitter)


def scan_up_axis(config: Any, data_dir: Path) -> int | None:
    """A scan-frame run's up axis (the data set's), which the ``aligned`` frame turns about
    and its validation turns its scans about when its training turns them
    (``augment_rotate``); ``None`` in the shape frame or for a data set whose manifest does
    not name it (then the ``aligned`` frame takes y)."""
    if getattr(config, "frame", "shape") == "shape":
        return None
    try:
        return up_axis_index(read_manifest(data_dir))
    except ConfigError:
        return None
