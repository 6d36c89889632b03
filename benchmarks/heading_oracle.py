"""What the aligned frame's half-turn ambiguity is worth: an aligned model run on each partial
as the frame gives it and turned by half a turn, and the better of the two per scan (an oracle).

Every shape of the split is cut at each of the five viewpoints (``--views 1``: the test
protocol's one, ``VIEWPOINTS[i % 5]``), put in its aligned frame, completed both ways
and scored in the data set's units (CD-L2 ×1000, mean over categories, and the median scan).

    python benchmarks/heading_oracle.py --data data/sh3d --split val --checkpoint sh3d-mirror
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from pfnet.data import load_split
from pfnet.data.scan_frame import scan_frame, up_rotation
from pfnet.evaluation.metrics import sample_metrics
from pfnet.geometry import VIEWPOINTS, crop_by_viewpoint


def category_mean(values: np.ndarray, categories: np.ndarray) -> float:
    """The mean of the per-category means, as the paper's tables take it."""
    return float(np.mean([values[categories == c].mean() for c in sorted(set(categories))]))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--split", default="val")
    parser.add_argument("--checkpoint", default="sh3d-mirror")
    parser.add_argument("--views", type=int, choices=(1, 5), default=5)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)

    from pfnet.inference.predict import network_input, predict_missing
    from pfnet.inference.runtimes import load_generator

    loaded = load_generator(args.checkpoint, runtime="torch", device="cpu")
    n_missing = int(loaded.model.n_missing)
    n_input = int(loaded.model.n_points) - n_missing
    clouds = load_split(args.data, args.split)
    half = up_rotation(np.pi, 1)
    partials, removed, frames, categories = [], [], [], []
    for i, cloud in enumerate(np.asarray(clouds.points, np.float32)):
        views = range(5) if args.views == 5 else [i % 5]
        for v in views:
            partial, missing = crop_by_viewpoint(
                cloud, np.asarray(VIEWPOINTS[v], np.float32), n_missing=n_missing
            )
            frame = scan_frame(partial, aligned=True)
            partials.append(network_input(frame.apply(partial), n_input))
            removed.append(missing)
            frames.append(frame)
            categories.append(str(clouds.category[i]))
    batch = np.stack(partials)
    as_given = predict_missing(loaded.model, batch, 32, "cpu")
    turned = predict_missing(loaded.model, (batch @ half.T).astype(np.float32), 32, "cpu") @ half
    scores = []
    for detail in (as_given, turned):
        mapped = [f.invert(d).astype(np.float32) for f, d in zip(frames, detail, strict=True)]
        scores.append(sample_metrics(mapped, removed)["cd_l2"] * 1000.0)
    categories = np.asarray(categories)
    rows = {
        "as the frame gives it": scores[0],
        "half a turn": scores[1],
        "the better of the two (oracle)": np.minimum(scores[0], scores[1]),
    }
    figures = {
        name: {"cd_l2": category_mean(v, categories), "median_cd_l2": float(np.median(v))}
        for name, v in rows.items()
    }
    figures["half a turn better"] = float(np.mean(scores[1] < scores[0]))
    print(f"{len(batch)} {args.split} partials of {args.data}, {args.checkpoint}:")
    print(json.dumps(figures, indent=2))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        document = {"data": str(args.data), "split": args.split, "views": args.views}
        document.update(checkpoint=args.checkpoint, figures=figures)
        args.json.write_text(json.dumps(document, indent=2) + "\n")


if __name__ == "__main__":
    main()
