"""Does the edge score point at the cut? No network: every shape of a split cut at each of
the five viewpoints, the edge score (:func:`pfnet.models.edge.edge_scores`) of every point of
the partial, and how the tenth with the highest scores sits against the removed points:

- ``near_hole``: the share of those points among the tenth of the partial nearest the removed
  points (chance: 0.1);
- ``cos``: the cosine between their centroid and the removed points' centroid, both taken
  from the partial's centroid (``hole_side``: the share of cuts where it is positive);
- ``sphere_cos`` / ``sphere_hole_side``: the same for the centre of a sphere fitted to those
  points (the crop removes a ball about the viewpoint, so the cut's rim lies on its surface):
  :data:`TRIALS` spheres through four of them at random, the one with the most of them within
  :data:`TOLERANCE` of its surface, less :data:`EMPTY_WEIGHT` for each point of the partial
  inside it (the ball is empty of the partial), radius under :data:`MAX_RADIUS`;
- the named cuts' own cosines (``--show``), for the scans that the scan protocol's worst tenth
  names.

    python benchmarks/edge_probe.py --data data/sh3d --split test [--show 53 30] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from pfnet.data import load_split
from pfnet.data.crops import missing_count
from pfnet.geometry import VIEWPOINTS, crop_by_viewpoint, nearest_neighbors
from pfnet.models.edge import NEIGHBOURS, edge_scores

TOP = 0.1  # the share of the partial's points, by edge score, that the probe follows
TRIALS = 800  # spheres tried per cut
TOLERANCE = 0.02  # of a sphere's surface, in the data set's units (shapes in the unit ball)
EMPTY_WEIGHT = 5  # a partial point inside a sphere costs this many rim points on it
MAX_RADIUS = 3.0


def _spheres(quads: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The spheres through ``(T, 4, 3)`` quadruples: centres ``(T, 3)`` and radii ``(T,)``
    (``inf`` where the four are coplanar)."""
    a = 2.0 * (quads[:, 1:] - quads[:, :1])
    b = (quads[:, 1:] ** 2).sum(-1) - (quads[:, :1] ** 2).sum(-1)
    solvable = np.abs(np.linalg.det(a)) > 1e-9
    centres = np.zeros((len(quads), 3))
    centres[solvable] = np.linalg.solve(a[solvable], b[solvable][..., None])[..., 0]
    radii = np.linalg.norm(quads[:, 0] - centres, axis=1)
    radii[~solvable] = np.inf
    return centres, radii


def rim_sphere(partial: np.ndarray, rim: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The centre of the sphere that best fits the ``rim`` points and holds none of
    ``partial`` (the figures of the module's docstring)."""
    quads = rim[rng.integers(0, len(rim), size=(TRIALS, 4))].astype(np.float64)
    centres, radii = _spheres(quads)
    keep = radii < MAX_RADIUS
    centres, radii = centres[keep], radii[keep]
    on = np.abs(np.linalg.norm(rim[None] - centres[:, None], axis=2) - radii[:, None])
    inside = np.linalg.norm(partial[None] - centres[:, None], axis=2) < radii[:, None] - TOLERANCE
    score = (on < TOLERANCE).sum(axis=1) - EMPTY_WEIGHT * inside.sum(axis=1)
    return centres[int(np.argmax(score))]


def _cos(a: np.ndarray, b: np.ndarray) -> float:
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b) + 1e-12))


def probe(
    cloud: np.ndarray, view: int, rng: np.random.Generator, ratio: float = 0.25
) -> dict[str, float]:
    """The figures of one cut of a complete ``(N, 3)`` cloud at ``VIEWPOINTS[view]``."""
    viewpoint = np.asarray(VIEWPOINTS[view], np.float32)
    partial, missing = crop_by_viewpoint(
        cloud, viewpoint, n_missing=missing_count(len(cloud), ratio)
    )
    scores = edge_scores(torch.from_numpy(partial)[None])[0].numpy()
    top = np.argsort(-scores, kind="stable")[: int(len(partial) * TOP)]
    to_hole = nearest_neighbors(partial, missing)[0]
    near = to_hole < np.quantile(to_hole, TOP)
    centre = partial.mean(axis=0)
    hole = missing.mean(axis=0) - centre
    sphere = rim_sphere(partial, partial[top], rng) - centre
    return {
        "near_hole": float(near[top].mean()),
        "cos": _cos(partial[top].mean(axis=0) - centre, hole),
        "sphere_cos": _cos(sphere, hole),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--split", default="test")
    parser.add_argument("--show", type=int, nargs="*", default=[], help="shapes to list")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    split = load_split(args.data, args.split)
    rows, shown = [], {}
    rng = np.random.default_rng(0)
    for j, cloud in enumerate(np.asarray(split.points, np.float32)):
        for view in range(len(VIEWPOINTS)):
            row = probe(cloud, view, rng)
            rows.append(row)
            if j in args.show and view == j % len(VIEWPOINTS):  # the cut the 54-scan test makes
                shown[f"{j:03d}-{split.category[j]}"] = row
    cos = np.array([r["cos"] for r in rows])
    out = {
        "data": args.data,
        "split": args.split,
        "cuts": len(rows),
        "neighbours": NEIGHBOURS,
        "near_hole": float(np.mean([r["near_hole"] for r in rows])),
        "near_hole_by_chance": TOP,
        "cos_mean": float(cos.mean()),
        "cos_median": float(np.median(cos)),
        "hole_side": float((cos > 0).mean()),
        "sphere_cos_median": float(np.median([r["sphere_cos"] for r in rows])),
        "sphere_hole_side": float(np.mean([r["sphere_cos"] > 0 for r in rows])),
        "shown": shown,
    }
    print(json.dumps(out, indent=2))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
