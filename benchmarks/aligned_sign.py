"""Which end of the aligned frame's main axis the hole is at: how often each sign rule puts the
removed points on +x.

The aligned frame (:func:`pfnet.data.scan_frame.scan_frame`) turns a partial so that its main
horizontal axis lies along x, pointing where the third moment of its points is positive. What
is left to the network is which end is cut. A rule that put the hole on +x every time would
leave it nothing to guess; this measures how far each rule is from that, with no network:
every shape of a split cut at each of the five viewpoints, the centroid of the removed points
in the partial's aligned frame, and the share of cuts whose centroid lies on the side a rule
points to (all cuts, and those whose hole lies mostly along the main axis: ``|x|`` over
``|x| + |z|`` of its centroid above ``ALONG``). The rules:

- ``third moment``: the frame's own sign;
- ``farther reach``: towards the extreme point farther from the centroid;
- ``sparser end``: towards the end with fewer points in its outer ``END_SHARE`` of the extent;
- ``rim``: towards the side of the cut's rim, the centroid of the tenth of the points with the
  highest edge scores (:func:`pfnet.data.rim.rim_centroid`). The ``aligned-rim`` frame uses
  the rim to choose among four directions, not two: ``benchmarks/frame_hole.py``.

    python benchmarks/aligned_sign.py --data data/sh3d --split train [--json FILE]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from pfnet.data import every_view, load_split
from pfnet.data.crops import missing_count
from pfnet.data.rim import rim_centroid
from pfnet.data.scan_frame import scan_frame
from pfnet.geometry import VIEWPOINTS, crop_by_viewpoint

ALONG = 0.6
"""A hole lies along the main axis when ``|x| / (|x| + |z|)`` of its centroid exceeds this."""
END_SHARE = 0.15
"""The outer share of the partial's extent along x that the sparser-end rule counts."""
RULES = ("third moment", "farther reach", "sparser end", "rim")


def rule_signs(x: np.ndarray, rim_x: float) -> dict[str, float]:
    """The side (+1 or -1) each rule points to, from the partial's x coordinates in its frame
    and that of its rim's centroid."""
    span = float(x.max() - x.min())
    low = int((x < x.min() + END_SHARE * span).sum())
    high = int((x > x.max() - END_SHARE * span).sum())
    return {
        "third moment": 1.0,  # the frame has already turned it to +x
        "farther reach": 1.0 if x.max() + x.min() >= 0 else -1.0,
        "sparser end": 1.0 if high <= low else -1.0,
        "rim": 1.0 if rim_x >= 0 else -1.0,
    }


def cut_rows(points: np.ndarray, ratio: float = 0.25) -> list[dict]:
    """For each complete cloud of ``points`` (``(S, N, 3)``, y up) cut at its test viewpoint
    (``VIEWPOINTS[j % 5]``): the hole's side and share along x in the aligned frame, and
    each rule's side."""
    rows = []
    n_missing = missing_count(points.shape[1], ratio)
    for j, cloud in enumerate(np.asarray(points, np.float32)):
        view = np.asarray(VIEWPOINTS[j % 5], np.float32)
        partial, missing = crop_by_viewpoint(cloud, view, n_missing=n_missing)
        frame = scan_frame(partial, aligned=True, up_axis=1)
        hole = frame.apply(missing).astype(np.float64).mean(axis=0)
        x = frame.apply(partial).astype(np.float64)[:, 0]
        rim_x = float(frame.apply(rim_centroid(partial)[None])[0, 0])
        along = abs(hole[0]) / (abs(hole[0]) + abs(hole[2]) + 1e-12)
        rows.append({"hole": 1.0 if hole[0] >= 0 else -1.0, "along": along, **rule_signs(x, rim_x)})
    return rows


def agreement(rows: list[dict], categories: np.ndarray) -> dict:
    """Per rule: the share of cuts whose hole is on its side, over all cuts, over those along
    the main axis, and per category."""
    hole = np.array([r["hole"] for r in rows])
    along = np.array([r["along"] for r in rows]) > ALONG
    out = {"cuts": len(rows), "along_the_main_axis": int(along.sum())}
    for rule in RULES:
        hit = np.array([r[rule] for r in rows]) == hole
        out[rule] = {
            "all": float(hit.mean()),
            "along": float(hit[along].mean()) if along.any() else None,
            "categories": {c: float(hit[categories == c].mean()) for c in sorted(set(categories))},
        }
    return out


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--split", default="train")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    clouds = every_view(load_split(args.data, args.split), 5)
    table = agreement(cut_rows(clouds.points), np.asarray(clouds.category))
    document = {"data": str(args.data), "split": args.split, "views": 5, **table}
    for rule in RULES:
        figures = table[rule]
        print(
            f"{rule:14s} hole on its side: {figures['all']:.3f} of {table['cuts']} cuts; "
            f"along the main axis {figures['along']:.3f} of {table['along_the_main_axis']}"
        )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(document, indent=2) + "\n")
    return document


if __name__ == "__main__":
    main()
