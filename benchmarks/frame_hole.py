"""Where each scan frame puts the hole: the share of cuts whose removed points lie on +x, and
the median cosine between +x and the horizontal direction of their centroid (no network).

A network trained in a frame learns where that frame tends to put the missing part; a frame
that puts it at +x every time leaves nothing of the hole's place to guess. Every shape of a
split is cut at each of the five viewpoints (25 % missing), the partial put in each frame of
:data:`FRAMES` (:func:`pfnet.data.scan_frame.frame_of`), and the centroid of the removed
points mapped through the same transform.

    python benchmarks/frame_hole.py --data data/sh3d --split test [--json FILE]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from pfnet.data import every_view, load_split
from pfnet.data.crops import missing_count
from pfnet.data.scan_frame import frame_of
from pfnet.geometry import VIEWPOINTS, crop_by_viewpoint

FRAMES = ("aligned", "aligned-end", "aligned-rim", "rim")


def hole_cosines(points: np.ndarray, ratio: float = 0.25) -> dict[str, np.ndarray]:
    """Per frame, the cosine between +x and the horizontal direction of each cut's hole (cloud
    ``j`` of ``(S, N, 3)`` y-up clouds cut at ``VIEWPOINTS[j % 5]``)."""
    n_missing = missing_count(points.shape[1], ratio)
    out: dict[str, list[float]] = {f: [] for f in FRAMES}
    for j, cloud in enumerate(np.asarray(points, np.float32)):
        view = np.asarray(VIEWPOINTS[j % 5], np.float32)
        partial, missing = crop_by_viewpoint(cloud, view, n_missing=n_missing)
        for frame in FRAMES:
            hole = frame_of(partial, frame).apply(missing).astype(np.float64).mean(axis=0)
            flat = hole[[0, 2]]
            out[frame].append(float(flat[0] / max(np.linalg.norm(flat), 1e-12)))
    return {f: np.array(c) for f, c in out.items()}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--split", default="test")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    clouds = every_view(load_split(args.data, args.split), 5)
    cosines = hole_cosines(clouds.points)
    document = {"data": str(args.data), "split": args.split, "views": 5, "cuts": len(clouds)}
    for frame, c in cosines.items():
        document[frame] = {"on_plus_x": float(np.mean(c > 0)), "median_cosine": float(np.median(c))}
        print(f"{frame:12s} hole on +x {np.mean(c > 0):.3f}, median cosine {np.median(c):.3f}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(document, indent=2) + "\n")
    return document


if __name__ == "__main__":
    main()
