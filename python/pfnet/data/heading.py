"""Reading a partial cloud's heading: its turn about the up axis away from the data set's frame.

A scan arrives in an unknown heading. The ``aligned`` frame (:mod:`pfnet.data.scan_frame`)
turns it to its own main horizontal axis, which leaves which end is which (and, for a shape
about as deep as wide, which axis is which) to the network. The heading reader is a small
PointNet that reads, from the partial in that aligned frame, where the main axis pointed in
the data set's frame: a distribution over :data:`~pfnet.models.heading.BINS` bins of that
angle. The aligned frame is the same for any heading of a scan, so the reader has no turn
to learn, only which way such a shape faces; the scan's own main axis then gives its heading
(:func:`aligned_input`, :meth:`HeadingReader.headings`). A model of the ``heading`` frame sees
each scan in the scan frame turned back by that heading, as it saw its training partials in
the data set's own heading. For a round shape the main axis is noise and so is the heading
read; such a shape looks alike from every side.

The reader runs in NumPy (no torch, so the light install reads headings too), from a
``safetensors`` file whose layers have their batch normalisation folded in
(:func:`pfnet.models.heading.save_reader` writes it from the trained torch module).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np

from pfnet.errors import DataError

FORMAT = "pfnet-heading-reader"
VERSION = "1"
SHIPPED = Path(__file__).parent.parent / "weights" / "heading" / "sh3d.safetensors"
"""The shipped reader, trained on SweetHome3D's furniture (its card is in the file)."""


@dataclass(frozen=True)
class HeadingReader:
    """A trained heading reader (:func:`load_reader`).

    Attributes:
        path: The file it was read from.
        bins: Number of bins over the full turn.
        points: Points of its input (farthest point samples of the partial).
        point_layers: ``(weight, bias)`` of the per-point layers (ReLU after each).
        head_layers: ``(weight, bias)`` of the layers after the max pool (ReLU between).
        card: What the file says about its training.
    """

    path: Path
    bins: int
    points: int
    point_layers: tuple[tuple[np.ndarray, np.ndarray], ...]
    head_layers: tuple[tuple[np.ndarray, np.ndarray], ...]
    card: dict

    def sample(self, partial: np.ndarray) -> np.ndarray:
        """``(points, 3)`` float32: the reader's input made of a normalised partial cloud
        (farthest point samples from point 0; a smaller cloud repeated cyclically)."""
        from pfnet.data.sampling import fixed_size

        return fixed_size(partial, self.points)

    def logits(self, samples: np.ndarray) -> np.ndarray:
        """``(B, bins)`` scores of ``(B, points, 3)`` reader inputs (:meth:`sample`)."""
        hidden = np.asarray(samples, np.float32)
        for weight, bias in self.point_layers:
            hidden = np.maximum(hidden @ weight.T + bias, 0.0)
        pooled = hidden.max(axis=1)
        for k, (weight, bias) in enumerate(self.head_layers):
            pooled = pooled @ weight.T + bias
            if k < len(self.head_layers) - 1:
                pooled = np.maximum(pooled, 0.0)
        return pooled

    def headings(self, partials: list[np.ndarray]) -> np.ndarray:
        """float64 ``(B,)`` headings in radians, in ``[0, 2π)``, of y-up partial clouds: the
        turn about the up axis that takes the data set's frame to each partial's (its main
        axis's angle less the angle the reader reads, :func:`decode_headings`)."""
        if not partials:
            return np.zeros(0)
        inputs = [aligned_input(p) for p in partials]
        samples = np.stack([self.sample(points) for points, _ in inputs])
        read = decode_headings(self.logits(samples))
        return (np.array([angle for _, angle in inputs]) - read) % (2 * math.pi)


def aligned_input(partial: np.ndarray) -> tuple[np.ndarray, float]:
    """A y-up partial cloud in its aligned frame (float32), and the angle of its main
    horizontal axis (radians, counter-clockwise from x seen from above: what the aligned
    frame turns by). The reader's target for a partial in the data set's heading is that
    angle; a partial turned by ``t`` has the same aligned cloud and its angle plus ``t``."""
    from pfnet.data.scan_frame import scan_frame

    frame = scan_frame(partial, aligned=True)
    rotation = frame.rotation  # up_rotation(-angle) about y
    return frame.apply(partial), float(np.arctan2(-rotation[2, 0], rotation[0, 0]))


def decode_headings(scores: np.ndarray) -> np.ndarray:
    """float64 ``(B,)`` headings in ``[0, 2π)`` from ``(B, bins)`` scores: the circular mean of
    the scores' softmax over the best bin and its two neighbours on each side (finer than a
    bin, and a reading of two modes keeps its best one)."""
    scores = np.asarray(scores, np.float64)
    bins = scores.shape[1]
    weights = np.exp(scores - scores.max(axis=1, keepdims=True))
    centres = (np.arange(bins) + 0.5) * (2 * math.pi / bins)
    near = (weights.argmax(axis=1)[:, None] + np.arange(-2, 3)[None, :]) % bins
    vectors = (np.take_along_axis(weights, near, axis=1) * np.exp(1j * centres[near])).sum(1)
    return np.angle(vectors) % (2 * math.pi)


def load_reader(path: str | os.PathLike[str] | None = None) -> HeadingReader:
    """A heading reader from its file (default: the shipped one), read once per path.

    Raises:
        DataError: The file is missing or is not a heading reader file (naming the path).
    """
    return _load(Path(SHIPPED if path is None else path).resolve())


@cache
def _load(path: Path) -> HeadingReader:
    from safetensors import safe_open

    if not path.is_file():
        raise DataError(f"heading reader {path} not found")
    try:
        with safe_open(str(path), framework="numpy") as handle:
            metadata = handle.metadata() or {}
            tensors = {key: handle.get_tensor(key) for key in handle.keys()}  # noqa: SIM118
    except Exception as err:  # safetensors raises its own error types for bad headers
        raise DataError(f"heading reader {path} cannot be read: {err}") from None
    if metadata.get("format") != FORMAT or metadata.get("version") != VERSION:
        raise DataError(f"{path} is not a pfnet heading reader file (version {VERSION})")
    try:
        bins, points = int(metadata["bins"]), int(metadata["points"])
        card = json.loads(metadata.get("card", "{}"))
        layers = {
            group: tuple(
                (
                    tensors[f"{group}.{k}.weight"].astype(np.float32),
                    tensors[f"{group}.{k}.bias"].astype(np.float32),
                )
                for k in range(int(metadata[f"{group}_layers"]))
            )
            for group in ("point", "head")
        }
    except (KeyError, ValueError, RecursionError) as err:
        raise DataError(f"heading reader {path} has a broken header: {err}") from None
    widths = [3] + [w.shape[0] for w, _ in layers["point"]]
    heads = [widths[-1]] + [w.shape[0] for w, _ in layers["head"]]
    shapes_ok = all(
        w.shape == (o, i) and b.shape == (o,)
        for (w, b), i, o in zip(
            layers["point"] + layers["head"],
            widths[:-1] + heads[:-1],
            widths[1:] + heads[1:],
            strict=True,
        )
    )
    if not shapes_ok or heads[-1] != bins or points < 1:
        raise DataError(f"heading reader {path}: its layers do not chain to {bins} bins")
    return HeadingReader(path, bins, points, layers["point"], layers["head"], card)
