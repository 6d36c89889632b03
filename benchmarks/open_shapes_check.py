"""The near-copy threshold and the leakage check of a prepared open-shapes corpus (issue 33).

Run on a data set prepared with several sources (or ``--distinct``) and ``--pool`` of at least
``4 × points`` (the open-shapes command uses 8192 for 2048 points)::

    python benchmarks/open_shapes_check.py data/open-shapes

1. **Threshold.** For every shape, four independent samples of its surface are at hand: the
   cloud and three slices of its pool. ``s1`` is the symmetric Chamfer distance between the
   cloud and the first slice, ``s2`` between the other two. ``s1 / s2`` is the ratio by which
   two samples of one surface are apart, in units of another estimate of the same thing:
   what ``prepare`` compares against ``NEAR_COPY_RATIO`` for a pair of identical meshes. Its
   quantiles show which share of identical surfaces a threshold catches.
2. **Leakage.** For every test and val shape, the nearest training shape (all categories;
   pairs whose sorted box sides differ by more than 0.1 are not compared) by the same ratio,
   ``d(T, R) / mean(s(T), s(R))`` with ``s`` from the pool. The check passes when none is at
   or below ``NEAR_COPY_RATIO``. The worst pairs are printed by name.

Prints a report (and writes it as JSON with ``--json PATH``); exits 1 when a shape leaks.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from pfnet.data.distinct import NEAR_COPY_RATIO, symmetric_chamfer
from pfnet.data.format import SPLITS, load_split, read_manifest

EXTENT_GAP = 0.1
BATCH = 4096


def _extents(clouds: np.ndarray) -> np.ndarray:
    return np.sort(clouds.max(axis=1) - clouds.min(axis=1), axis=1)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("data", type=Path)
    parser.add_argument("--ratio", type=float, default=NEAR_COPY_RATIO)
    parser.add_argument("--json", type=Path, help="also write the report here")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    manifest = read_manifest(args.data)
    splits = {split: load_split(args.data, split) for split in SPLITS}
    n = int(manifest["points"])
    clouds, pools, names, categories, split_of = [], [], [], [], []
    for split, data in splits.items():
        if data.extra is None or data.extra.shape[1] < 3 * n:
            print(f"{split}: needs a pool of at least {4 * n} points (prepare --pool)")
            return 2
        clouds.append(data.points)
        pools.append(data.extra[:, : 3 * n])
        names += data.name.tolist()
        categories += data.category.tolist()
        split_of += [split] * len(data.name)
    cloud = np.concatenate(clouds)
    pool = np.concatenate(pools)
    names_a = np.array(names)
    category = np.array(categories)
    split_a = np.array(split_of)
    # 1. two samples of one surface, in units of two others
    s1 = np.concatenate(
        [
            symmetric_chamfer(cloud[k : k + 256], pool[k : k + 256, :n])
            for k in range(0, len(cloud), 256)
        ]
    )
    s2 = np.concatenate(
        [
            symmetric_chamfer(pool[k : k + 256, n : 2 * n], pool[k : k + 256, 2 * n : 3 * n])
            for k in range(0, len(cloud), 256)
        ]
    )
    noise = s1 / s2
    quantiles = {q: float(np.quantile(noise, q)) for q in (0.5, 0.9, 0.99, 0.999)}
    caught = float((noise <= args.ratio).mean())
    print(
        f"two samples of one surface, ratio s1/s2 over {len(noise)} shapes: median "
        f"{quantiles[0.5]:.3f}, 90% {quantiles[0.9]:.3f}, 99% {quantiles[0.99]:.3f}, "
        f"99.9% {quantiles[0.999]:.3f}, max {noise.max():.3f}; within {args.ratio}: "
        f"{100 * caught:.2f} %"
    )
    # self-distance of each shape, from the pool (independent of what prepare used)
    self_d = 0.5 * (s1 + s2)
    # 2. every test/val shape against every training shape
    train = np.flatnonzero(split_a == "train")
    extents = _extents(cloud)
    report = {"threshold": {"ratio": args.ratio, "noise_quantiles": quantiles, "caught": caught}}
    for split in ("test", "val"):
        held = np.flatnonzero(split_a == split)
        i, j = np.meshgrid(held, train, indexing="ij")
        i, j = i.ravel(), j.ravel()
        close = np.abs(extents[i] - extents[j]).max(axis=1) <= EXTENT_GAP
        i, j = i[close], j[close]
        best = np.full(len(cloud), np.inf)
        best_j = np.full(len(cloud), -1)
        for k in range(0, len(i), BATCH):
            a, b = i[k : k + BATCH], j[k : k + BATCH]
            r = symmetric_chamfer(cloud[a], cloud[b]) / (0.5 * (self_d[a] + self_d[b]))
            for x, y, value in zip(a, b, r, strict=True):
                if value < best[x]:
                    best[x], best_j[x] = value, y
        ratios = best[held]
        leaks = int((ratios <= args.ratio).sum())
        order = np.argsort(ratios)[:8]
        worst = [
            {
                "held": str(names_a[held[o]]),
                "train": str(names_a[best_j[held[o]]]) if best_j[held[o]] >= 0 else None,
                "category": str(category[held[o]]),
                "train_category": str(category[best_j[held[o]]]) if best_j[held[o]] >= 0 else None,
                "ratio": float(ratios[o]),
            }
            for o in order
        ]
        finite = ratios[np.isfinite(ratios)]
        report[split] = {
            "shapes": len(held),
            "pairs_compared": len(i),
            "pairs_total": len(held) * len(train),
            "leaks": leaks,
            "nearest_ratio_min": float(finite.min()) if finite.size else None,
            "nearest_ratio_median": float(np.median(finite)) if finite.size else None,
            "worst": worst,
        }
        print(
            f"{split}: {len(held)} shapes, {len(i)} of {len(held) * len(train)} pairs with "
            f"train compared; nearest training shape at ratio min "
            f"{report[split]['nearest_ratio_min']:.3f}, median "
            f"{report[split]['nearest_ratio_median']:.3f}; at or below {args.ratio}: {leaks}"
        )
        for w in worst[:5]:
            print(
                f"    {w['held']} ({w['category']}) ~ {w['train']} ({w['train_category']}): "
                f"{w['ratio']:.3f}"
            )
    report["seconds"] = time.perf_counter() - start
    print(f"in {report['seconds']:.0f} s")
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))
    return 0 if report["test"]["leaks"] == 0 and report["val"]["leaks"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
