"""Write a few shapes per category of a prepared data set as ``.npy`` clouds, for a gallery.

    python benchmarks/open_shapes_export.py data/open-shapes /tmp/gallery \\
        --categories airplane,helicopter,car,truck,ship --per-category 3
    pfnet render /tmp/gallery/*.npy --role ground-truth --out docs/open-shapes-gallery.png

Shapes are taken from the test split first, in name order, spread over the category (every
k-th name), so that the same data set gives the same gallery.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from pfnet.data.format import SPLITS, load_split


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("data", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--categories", required=True)
    parser.add_argument("--per-category", type=int, default=3)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    splits = {split: load_split(args.data, split) for split in ("test", *SPLITS)}
    for rank, category in enumerate(args.categories.split(",")):
        shapes = sorted(
            (str(name), cloud)
            for data in splits.values()
            for name, cloud, c in zip(data.name, data.points, data.category, strict=True)
            if c == category
        )
        shapes = list(dict(shapes).items())
        step = max(1, len(shapes) // args.per_category)
        for k, (name, cloud) in enumerate(shapes[::step][: args.per_category]):
            np.save(args.out / f"{rank:02d}-{category}-{k}-{name}.npy", cloud)
    print(f"wrote {len(list(args.out.glob('*.npy')))} clouds to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
