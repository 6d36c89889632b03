"""KITTI's minimal matching distance (MMD) at the benchmark's real sizes, against the anchor.

The real evaluation (PoinTr ``KITTI_metric.py``) compares each of 2,401 completions of 16,384
points with every one of 5,927 ShapeNet cars (PCN's car category, train + val + test, 16,384
points each) by CD-L2 and keeps the smallest. The data are not here, so this builds a
synthetic set of the same sizes: car-like bodies (a box with a cabin on top, proportions drawn
per car) sampled on their surfaces, and completions that are perturbed copies of random cars.

Run: ``python benchmarks/bench_kitti.py [--completions 16] [--references 5927]``. It times
pfnet's exact branch-and-bound search
(:func:`pfnet.evaluation.metrics.minimal_matching_distance`) on a subset of completions
against the whole reference set, and once with no completion (the one-off cost: every car's
KD-tree) to separate the cost a completion;
checks its answers on a few completions against the anchor (every pair, scipy ``cKDTree`` /
pykdtree in a Python loop, as the peers' scripts do on a GPU), times the anchor per pair, and
projects both to 2,401 × 5,927 (pfnet's costs scaled linearly with the number of cars, which
overstates it: the completion's distance grid is shared by all the cars).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

FULL_COMPLETIONS = 2401
FULL_REFERENCES = 5927
POINTS = 16384


def car(rng: np.random.Generator, params: np.ndarray, n: int) -> np.ndarray:
    """``n`` points on a body box and a cabin box; ``params`` = length, width, height, cabin."""
    length, width, height, cabin = params
    boxes = [
        (np.array([0.0, 0.0, height / 2]), np.array([length, width, height])),
        (np.array([-0.1 * length, 0.0, height * 1.25]), np.array([cabin, width * 0.9, height / 2])),
    ]
    faces = []
    for centre, size in boxes:
        for axis in range(3):
            others = [a for a in range(3) if a != axis]
            area = size[others[0]] * size[others[1]]
            for sign in (-1, 1):
                faces.append((centre, size, axis, others, sign, area))
    areas = np.array([f[5] for f in faces])
    pick = rng.choice(len(faces), size=n, p=areas / areas.sum())
    points = np.empty((n, 3))
    for k, (centre, size, axis, others, sign, _) in enumerate(faces):
        sel = pick == k
        m = int(sel.sum())
        p = np.empty((m, 3))
        p[:, axis] = sign * size[axis] / 2
        for a in others:
            p[:, a] = rng.uniform(-size[a] / 2, size[a] / 2, m)
        points[sel] = p + centre
    points -= points.mean(axis=0)
    return (points / np.linalg.norm(points, axis=1).max()).astype(np.float32)


def car_params(rng: np.random.Generator, count: int) -> np.ndarray:
    return np.column_stack(
        [
            rng.uniform(3.6, 5.2, count),
            rng.uniform(1.5, 2.1, count),
            rng.uniform(0.6, 1.1, count),
            rng.uniform(1.4, 2.8, count),
        ]
    )


def anchor_pair(comp_tree, comp: np.ndarray, ref_tree, ref: np.ndarray) -> float:
    d1, _ = ref_tree.query(comp)
    d2, _ = comp_tree.query(ref)
    return float(np.mean(d1.astype(np.float64) ** 2) + np.mean(d2.astype(np.float64) ** 2))


def main() -> None:
    from scipy.spatial import cKDTree

    from pfnet.evaluation.metrics import minimal_matching_distance

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--completions", type=int, default=16)
    parser.add_argument("--references", type=int, default=FULL_REFERENCES)
    parser.add_argument("--anchor-pairs", type=int, default=40)
    parser.add_argument(
        "--check", type=int, default=2, help="completions checked against every pair (slow)"
    )
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    start = time.perf_counter()
    ref_params = car_params(rng, args.references)
    references = np.stack([car(rng, p, POINTS) for p in ref_params])
    source = rng.integers(0, args.references, args.completions)
    completions = np.stack(
        [car(rng, ref_params[j] * rng.uniform(0.97, 1.03, 4), POINTS) for j in source]
    )
    print(
        f"synthetic set: {args.references} cars, {args.completions} completions of {POINTS} "
        f"points ({time.perf_counter() - start:.1f} s to build)"
    )

    minimal_matching_distance([], references)  # warm-up: the first call pays page faults
    start = time.perf_counter()
    minimal_matching_distance([], references)
    fixed = time.perf_counter() - start
    start = time.perf_counter()
    distance, index = minimal_matching_distance(completions, references)
    ours = time.perf_counter() - start
    each = max(ours - fixed, 0.0) / args.completions  # wall time, completions in parallel
    print(
        f"pfnet MMD search: {ours:.2f} s for {args.completions} completions, of which "
        f"{fixed:.2f} s builds the {args.references} cars' trees: {each:.3f} s a completion"
    )

    # the anchor: every pair, KD-trees (pykdtree if installed, else scipy) in a Python loop
    try:
        from pykdtree.kdtree import KDTree as Tree

        anchor_name = "pykdtree"
    except ImportError:  # pragma: no cover
        Tree, anchor_name = cKDTree, "scipy cKDTree"
    comp_tree = Tree(completions[0])
    start = time.perf_counter()
    trees = [Tree(references[j]) for j in range(args.anchor_pairs)]
    for j in range(args.anchor_pairs):
        anchor_pair(comp_tree, completions[0], trees[j], references[j])
    per_pair = (time.perf_counter() - start) / args.anchor_pairs
    # exactness: the anchor's minimum over every car, for two completions
    for k in range(min(args.check, args.completions)):
        tree = Tree(completions[k])
        full = [
            anchor_pair(tree, completions[k], cKDTree(references[j]), references[j])
            for j in range(args.references)
        ]
        j = int(np.argmin(full))
        print(
            f"check completion {k}: pfnet {distance[k]:.9f} (car {index[k]}), "
            f"anchor {full[j]:.9f} (car {j})"
        )
        assert index[k] == j and abs(distance[k] - full[j]) <= 1e-6 * full[j]
    pairs = FULL_COMPLETIONS * FULL_REFERENCES
    scale = FULL_REFERENCES / args.references
    print(f"anchor ({anchor_name}, every pair): {per_pair * 1000:.1f} ms a pair")
    projected = (fixed + each * FULL_COMPLETIONS) * scale
    print(
        f"projected full KITTI MMD (2,401 x 5,927): pfnet {projected / 60:.1f} min; anchor "
        f"{per_pair * pairs / 3600:.0f} h on one process"
    )


if __name__ == "__main__":
    main()
