"""A data set without the shapes another one holds out: DATA minus the val and test shapes of
HELD, so that a model trained on DATA can be scored on HELD's test split honestly.

The open-shapes corpus contains the SweetHome3D furniture catalogue, split anew among the
corpus's own categories, so some of data/sh3d's test shapes sit in its training split. This
writes a copy of DATA whose train split (and val split) leaves out every shape named in
HELD's val or test split (shapes keep their names across data sets built from one source):

    python benchmarks/hold_out.py data/open-shapes --held data/sh3d --out data/open-shapes-x

It prints how many shapes it left out of each split; the manifest records them.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from pfnet.data.format import (
    SPLITS,
    CloudSet,
    load_split,
    read_manifest,
    split_record,
    write_dataset,
)


def held_names(held: Path) -> set[str]:
    """The names of the shapes in ``held``'s val and test splits."""
    return {str(name) for split in ("val", "test") for name in load_split(held, split).name}


def without(clouds: CloudSet, names: set[str]) -> tuple[CloudSet, list[str]]:
    """``clouds`` without the shapes named in ``names``, and the names left out."""
    keep = np.array([str(name) not in names for name in clouds.name], dtype=bool)
    extra = None if clouds.extra is None else clouds.extra[keep]
    kept = CloudSet(clouds.points[keep], clouds.category[keep], clouds.name[keep], extra)
    return kept, sorted(str(name) for name in clouds.name[~keep])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data", type=Path, help="the data set to copy")
    parser.add_argument("--held", type=Path, required=True, help="the data set held out")
    parser.add_argument("--out", type=Path, required=True, help="the folder to write")
    args = parser.parse_args(argv)
    names = held_names(args.held)
    manifest = read_manifest(args.data)
    splits, left_out = {}, {}
    for split in SPLITS:
        clouds = load_split(args.data, split)
        # the test split stays whole: a shape of both test splits is fair to score
        splits[split], left_out[split] = (clouds, []) if split == "test" else without(clouds, names)
        print(f"{split}: kept {len(splits[split])}, left out {len(left_out[split])}")
    manifest = dict(manifest)
    manifest["splits"] = {split: split_record(clouds) for split, clouds in splits.items()}
    manifest["held_out"] = {"data": str(args.held), "left_out": left_out}
    write_dataset(args.out, splits, json.loads(json.dumps(manifest)))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
