"""The nearest training crop: a completion that learns nothing but looks the scan up among the
training shapes' crops (a baseline of the scan protocol, beside the mirror of the input).

The bank: every training shape turned about the up axis by ``turns`` angles (evenly spaced
from a random offset per shape, so that no crop sits at the test protocol's own pose: the
protocol cuts the shapes unturned) and cut at each of the paper's five viewpoints, as a
network trained with ``--augment-rotate`` sees them; each crop's partial and missing points in
the partial's ``aligned`` frame. A scan, upright, is put in its own aligned frame; since that
frame leaves which end of the main axis is which to guess, the scan and its half turn are both
looked up. Each is shortlisted among the bank by a coarse occupancy descriptor, the shortlist
ranked by the Chamfer distance between farthest-point samples of the two partials, and the
best crop's missing points, in the same frame, mapped back into the scan's coordinates, are
the completion.

``python benchmarks/scan_protocol.py --nearest data/sh3d-all`` scores it beside the model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pfnet.data.sampling import fixed_size
from pfnet.data.scan_frame import scan_frame, up_rotation
from pfnet.geometry import VIEWPOINTS, chamfer, crop_by_viewpoint

SAMPLES = 512
"""Farthest-point samples of each partial that the Chamfer ranking compares."""

GRID = 8
"""Cells per side of the descriptor's occupancy grid over [-1.2, 1.2]³."""

SHORTLIST = 64
"""Crops of the bank ranked by Chamfer distance for each look-up."""


@dataclass(frozen=True)
class CropBank:
    """Training crops in their partials' aligned frames.

    Attributes:
        partials: float32 ``(C, SAMPLES, 3)``.
        missing: float32 ``(C, M, 3)``.
        descriptors: float32 ``(C, GRID³)``.
        shapes: int ``(C,)`` the training shape of each crop.
    """

    partials: np.ndarray
    missing: np.ndarray
    descriptors: np.ndarray
    shapes: np.ndarray


def descriptor(points: np.ndarray) -> np.ndarray:
    """The square roots of the shares of points in each cell of a ``GRID³`` grid over
    ``[-1.2, 1.2]³`` (the normalised partial and a margin): their distance compares shapes."""
    cells = np.clip(((np.asarray(points) + 1.2) / 2.4 * GRID).astype(int), 0, GRID - 1)
    flat = (cells[:, 0] * GRID + cells[:, 1]) * GRID + cells[:, 2]
    return np.sqrt(np.bincount(flat, minlength=GRID**3) / len(points)).astype(np.float32)


def _samples(points: np.ndarray) -> np.ndarray:
    return fixed_size(points, SAMPLES)


def crop_bank(clouds: np.ndarray, n_missing: int, *, turns: int = 8, seed: int = 0) -> CropBank:
    """The bank of ``(S, N, 3)`` y-up training clouds (module doc)."""
    rng = np.random.default_rng(seed)
    partials, missing, descriptors, shapes = [], [], [], []
    for s, cloud in enumerate(np.asarray(clouds, np.float32)):
        offset = rng.random()
        for k in range(turns):
            turn = up_rotation(2 * np.pi * (k + offset) / turns, 1).astype(np.float32)
            turned = np.ascontiguousarray(cloud @ turn.T)
            for view in VIEWPOINTS:
                partial, removed = crop_by_viewpoint(
                    turned, np.asarray(view, np.float32), n_missing=n_missing
                )
                frame = scan_frame(partial, aligned=True)
                seen = frame.apply(partial)
                partials.append(_samples(seen))
                missing.append(frame.apply(removed))
                descriptors.append(descriptor(seen))
                shapes.append(s)
    return CropBank(
        np.stack(partials), np.stack(missing), np.stack(descriptors), np.asarray(shapes)
    )


def nearest_crops(
    bank: CropBank, seen: np.ndarray, count: int = 1, *, shortlist: int = SHORTLIST
) -> list[tuple[float, int, np.ndarray]]:
    """The ``count`` crops of the bank nearest ``seen`` (a scan already in its aligned frame),
    best first, looked up as given and turned by half a turn: for each its Chamfer distance,
    its index in the bank and the turn that takes the bank's frame to ``seen``'s (its missing
    points in ``seen``'s frame are ``bank.missing[index] @ turn``)."""
    found = []
    for half_turns in (0, 1):
        turn = up_rotation(np.pi * half_turns, 1).astype(np.float32)
        query = seen @ turn.T
        gaps = ((bank.descriptors - descriptor(query)) ** 2).sum(axis=1)
        top = np.argsort(gaps, kind="stable")[: min(shortlist, len(gaps))]
        samples = np.broadcast_to(_samples(query), (len(top), SAMPLES, 3)).copy()
        to_crop, to_query = chamfer(samples, bank.partials[top])
        found += [(float(d), int(i), turn) for d, i in zip(to_crop + to_query, top, strict=True)]
    found.sort(key=lambda entry: entry[0])  # stable: ties keep the unturned look-up first
    return found[:count]


def nearest_completion(
    bank: CropBank, scan: np.ndarray, *, shortlist: int = SHORTLIST
) -> tuple[np.ndarray, int]:
    """The missing points of the crop nearest a y-up ``scan``, in the scan's coordinates,
    and that crop's index in the bank."""
    frame = scan_frame(scan, aligned=True)
    _, index, turn = nearest_crops(bank, frame.apply(scan), shortlist=shortlist)[0]
    return frame.invert(bank.missing[index] @ turn), index
