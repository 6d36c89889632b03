"""What the aligned frame's ambiguities are worth: an aligned model run on each partial as the
frame gives it, reflected across its main axis, turned by half a turn, and both; the better
candidate per scan (an oracle), and three rules that pick one from the scan alone.

Every shape of the split is cut at each of the five viewpoints (``--views 1``: the test
protocol's one, ``VIEWPOINTS[i % 5]``), put in its aligned frame, completed each way (the
prediction mapped back through the same reflection or turn) and scored in the data set's
units (CD-L2 ×1000, mean over categories, and the median scan). The rules: the candidate
whose prediction reaches farthest from the partial (the largest distance of a predicted point
to its nearest partial point), and the one with the fewest predicted points on the partial
(within 0.03 of a partial point, in the frame's units), and the one whose prediction lies
nearest the partial's mirror images (:func:`pfnet.data.symmetry.mirror_images`: the mean
distance of a predicted point to its nearest image; a scan without images keeps the frame's
candidate).

With ``--bank DATA`` two more rules use shape knowledge instead of the scan's geometry: each
scan is looked up among DATA's training shapes cut at the five viewpoints from eight sides
(:mod:`pfnet.evaluation.nearest`), and the candidate whose prediction lies nearest the
nearest crop's missing points (their symmetric mean distance) is picked; or each of the
``--votes`` nearest crops votes for the candidate nearest its missing points.

    python benchmarks/heading_oracle.py --data data/sh3d --split val --checkpoint sh3d-mirror \
        [--bank data/sh3d-all]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from pfnet.data import load_split
from pfnet.data.scan_frame import ALIGNED_FRAMES, frame_of, up_rotation
from pfnet.data.symmetry import mirror_images
from pfnet.evaluation.metrics import sample_metrics
from pfnet.geometry import VIEWPOINTS, crop_by_viewpoint, nearest_neighbors

ON_PARTIAL = 0.03
"""A predicted point this close to a partial point (the frame's units) lies on the partial."""


def category_mean(values: np.ndarray, categories: np.ndarray) -> float:
    """The mean of the per-category means, as the paper's tables take it."""
    return float(np.mean([values[categories == c].mean() for c in sorted(set(categories))]))


def mirror_distance(detail: np.ndarray, images: list[np.ndarray]) -> np.ndarray:
    """Per scan, the mean distance of a predicted point to the nearest of the scan's mirror
    images; 0 for a scan without images (every candidate ties, and the first is kept)."""
    out = np.zeros(len(detail))
    for i, (points, image) in enumerate(zip(detail, images, strict=True)):
        if len(image):
            out[i] = np.sqrt(nearest_neighbors(points.astype(np.float32), image)[0]).mean()
    return out


def symmetric_distance(a: np.ndarray, b: np.ndarray) -> float:
    """The mean distance of ``a``'s points to ``b`` plus that of ``b``'s to ``a``."""
    a, b = np.asarray(a, np.float32), np.asarray(b, np.float32)
    return float(
        np.sqrt(nearest_neighbors(a, b)[0]).mean() + np.sqrt(nearest_neighbors(b, a)[0]).mean()
    )


def retrieved_holes(bank_data: Path, partials, frames, n_points, n_missing, votes):
    """Per scan, the missing points of its ``votes`` nearest training crops, best first, in
    the scan's model frame (the look-up runs in the partial's own aligned frame)."""
    from pfnet.evaluation.nearest import crop_bank, nearest_crops

    clouds = np.asarray(load_split(bank_data, "train").points, np.float32)[:, :n_points]
    bank = crop_bank(clouds, n_missing)
    holes = []
    for partial, frame in zip(partials, frames, strict=True):
        aligned = frame_of(partial, "aligned")
        found = nearest_crops(bank, aligned.apply(partial), votes)
        holes.append([frame.apply(aligned.invert(bank.missing[i] @ turn)) for _, i, turn in found])
    return holes


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--split", default="val")
    parser.add_argument("--checkpoint", default="sh3d-mirror")
    parser.add_argument("--views", type=int, choices=(1, 5), default=5)
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--bank", type=Path, default=None, help="training shapes to look up")
    parser.add_argument("--votes", type=int, default=8)
    args = parser.parse_args(argv)

    from pfnet.inference.predict import network_input, predict_missing
    from pfnet.inference.runtimes import load_generator

    loaded = load_generator(args.checkpoint, runtime="torch", device="cpu")
    n_missing = int(loaded.model.n_missing)
    n_input = int(loaded.model.n_points) - n_missing
    frame_name = loaded.config.frame  # aligned or aligned-end: the model's own
    if frame_name not in ALIGNED_FRAMES:
        raise SystemExit(
            f"{args.checkpoint} was trained in frame {frame_name!r}, not an aligned one"
        )
    clouds = load_split(args.data, args.split)
    partials, originals, removed, frames, categories = [], [], [], [], []
    for i, cloud in enumerate(np.asarray(clouds.points, np.float32)):
        views = range(5) if args.views == 5 else [i % 5]
        for v in views:
            partial, missing = crop_by_viewpoint(
                cloud, np.asarray(VIEWPOINTS[v], np.float32), n_missing=n_missing
            )
            frame = frame_of(partial, frame_name)
            partials.append(network_input(frame.apply(partial), n_input))
            originals.append(partial)
            removed.append(missing)
            frames.append(frame)
            categories.append(str(clouds.category[i]))
    batch = np.stack(partials)
    reflect = np.diag([1.0, 1.0, -1.0])  # across the vertical plane through the main axis
    half = up_rotation(np.pi, 1)
    candidates = {
        "as the frame gives it": np.eye(3),
        "reflected": reflect,
        "half a turn": half,
        "half a turn, reflected": half @ reflect,
    }
    images = [mirror_images(p, up_axis=1) for p in batch]
    holes = None
    if args.bank is not None:
        holes = retrieved_holes(
            args.bank, originals, frames, clouds.points.shape[1], n_missing, args.votes
        )
    scores, reach, on_partial, off_mirror, off_holes = [], [], [], [], []
    for transform in candidates.values():  # orthogonal: its inverse is its transpose
        moved = (batch @ transform.T).astype(np.float32)
        detail = predict_missing(loaded.model, moved, 32, "cpu") @ transform
        mapped = [f.invert(d).astype(np.float32) for f, d in zip(frames, detail, strict=True)]
        scores.append(sample_metrics(mapped, removed)["cd_l2"] * 1000.0)
        distance = np.sqrt(nearest_neighbors(detail.astype(np.float32), batch)[0])
        reach.append(distance.max(axis=1))
        on_partial.append((distance < ON_PARTIAL).mean(axis=1))
        off_mirror.append(mirror_distance(detail, images))
        if holes is not None:
            off_holes.append(
                [
                    [symmetric_distance(d, h) for h in hs]
                    for d, hs in zip(detail, holes, strict=True)
                ]
            )
    scores, reach, on_partial, off_mirror = (
        np.stack(v, axis=1) for v in (scores, reach, on_partial, off_mirror)
    )
    scans = np.arange(len(batch))
    categories = np.asarray(categories)
    rows = {name: scores[:, k] for k, name in enumerate(candidates)}
    rows["the better of the two turns (oracle)"] = scores[:, [0, 2]].min(axis=1)
    rows["the best of the four (oracle)"] = scores.min(axis=1)
    for name, pick in (
        ("the farthest reach, of the two turns", 2 * reach[:, [0, 2]].argmax(axis=1)),
        ("the farthest reach, of the four", reach.argmax(axis=1)),
        ("the fewest on the partial, of the two turns", 2 * on_partial[:, [0, 2]].argmin(axis=1)),
        ("the fewest on the partial, of the four", on_partial.argmin(axis=1)),
        (
            "the nearest the mirror images, of the two turns",
            2 * off_mirror[:, [0, 2]].argmin(axis=1),
        ),
        ("the nearest the mirror images, of the four", off_mirror.argmin(axis=1)),
    ):
        rows[name] = scores[scans, pick]
    if holes is not None:
        off_holes = np.asarray(off_holes)  # (candidate, scan, crop)
        nearest = off_holes[:, :, 0].T
        ballots = off_holes.argmin(axis=0)  # (scan, crop): each crop's candidate
        tally = np.stack([(ballots == k).sum(axis=1) for k in range(4)], axis=1)
        for name, pick in (
            ("the nearest the retrieved hole, of the two turns", 2 * nearest[:, [0, 2]].argmin(1)),
            ("the nearest the retrieved hole, of the four", nearest.argmin(axis=1)),
            (f"the vote of {args.votes} retrieved holes, of the four", tally.argmax(axis=1)),
        ):
            rows[name] = scores[scans, pick]
    figures = {
        name: {"cd_l2": category_mean(v, categories), "median_cd_l2": float(np.median(v))}
        for name, v in rows.items()
    }
    figures["half a turn better"] = float(np.mean(scores[:, 2] < scores[:, 0]))
    print(f"{len(batch)} {args.split} partials of {args.data}, {args.checkpoint}:")
    print(json.dumps(figures, indent=2))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        document = {"data": str(args.data), "split": args.split, "views": args.views}
        if args.bank is not None:
            document.update(bank=str(args.bank), votes=args.votes)
        document.update(checkpoint=args.checkpoint, figures=figures)
        args.json.write_text(json.dumps(document, indent=2) + "\n")


if __name__ == "__main__":
    main()
