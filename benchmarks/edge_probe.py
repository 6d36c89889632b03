"""Does the edge score point at the cut? No network: every shape of a split cut at each of
the five viewpoints, the edge score (:func:`pfnet.models.edge.edge_scores`) of every point of
the partial, and how the tenth with the highest scores sits against the removed points:

- ``near_hole``: the share of those points among the tenth of the partial nearest the removed
  points (chance: 0.1);
- ``cos``: the cosine between their centroid and the removed points' centroid, both taken
  from the partial's centroid (``hole_side``: the share of cuts where it is positive);
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


def probe(cloud: np.ndarray, view: int, ratio: float = 0.25) -> dict[str, float]:
    """The two figures of one cut of a complete ``(N, 3)`` cloud at ``VIEWPOINTS[view]``."""
    viewpoint = np.asarray(VIEWPOINTS[view], np.float32)
    partial, missing = crop_by_viewpoint(
        cloud, viewpoint, n_missing=missing_count(len(cloud), ratio)
    )
    scores = edge_scores(torch.from_numpy(partial)[None])[0].numpy()
    top = np.argsort(-scores, kind="stable")[: int(len(partial) * TOP)]
    to_hole = nearest_neighbors(partial, missing)[0]
    near = to_hole < np.quantile(to_hole, TOP)
    centre = partial.mean(axis=0)
    edge, hole = partial[top].mean(axis=0) - centre, missing.mean(axis=0) - centre
    cos = float(edge @ hole / (np.linalg.norm(edge) * np.linalg.norm(hole) + 1e-12))
    return {"near_hole": float(near[top].mean()), "cos": cos}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--split", default="test")
    parser.add_argument("--show", type=int, nargs="*", default=[], help="shapes to list")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    split = load_split(args.data, args.split)
    rows, shown = [], {}
    for j, cloud in enumerate(np.asarray(split.points, np.float32)):
        for view in range(len(VIEWPOINTS)):
            row = probe(cloud, view)
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
        "shown": shown,
    }
    print(json.dumps(out, indent=2))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
