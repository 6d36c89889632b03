"""``pfnet prepare``: build a completion dataset from meshes, ShapeNet-Part, SweetHome3D,
procedural shapes, or the PCN, ShapeNet-55/34 and KITTI benchmarks."""

from __future__ import annotations

import argparse
from pathlib import Path

from pfnet.data.sources.registry import FORMATS
from pfnet.errors import ConfigError

HELP = "Build a completion dataset (sampled, normalised point clouds) from a source."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``pfnet prepare``."""
    parser.add_argument(
        "source",
        metavar="SOURCE",
        nargs="+",
        help="a folder (ROOT/<category>/<mesh>, a ShapeNet-Part, PCN, ShapeNet-55/34 or KITTI "
        "tree, *.sh3f catalogues, a FlightGear, TORCS or crrcsim data tree, the SweetHome3D "
        "application's folder or jar), a .sh3f file, or the word 'procedural'; several mesh "
        "and catalogue sources make one data set",
    )
    parser.add_argument("--out", required=True, metavar="DIR", help="dataset folder to write")
    parser.add_argument(
        "--format",
        default="auto",
        choices=(
            "auto",
            *FORMATS,
            "pcn",
            "shapenet-55",
            "shapenet-34",
            "shapenet-unseen21",
            "kitti",
        ),
        help="source format (default: auto-detect)",
    )
    parser.add_argument(
        "--points",
        type=int,
        default=None,
        help="points per shape (default 2048; the benchmarks keep their own)",
    )
    parser.add_argument(
        "--seed", type=int, default=0, help="seed of sampling and splits (default 0)"
    )
    parser.add_argument(
        "--test-fraction",
        type=float,
        default=0.2,
        help="share of each category for test, when the source has no split (default 0.2)",
    )
    parser.add_argument(
        "--val-fraction",
        type=float,
        default=0.1,
        help="share of each category for val, when the source has no split (default 0.1)",
    )
    parser.add_argument(
        "--categories",
        metavar="A,B",
        help="comma-separated categories to keep; 'all' also keeps SweetHome3D's unmatched "
        "'other' models",
    )
    parser.add_argument(
        "--workers", type=int, help="worker processes (default: all usable CPU cores)"
    )
    parser.add_argument("--count", type=int, help="procedural shapes per category (default 100)")
    parser.add_argument(
        "--pool",
        type=int,
        metavar="N",
        help="also store N points per shape in all (more than --points): the cloud and more "
        "of the same surface, from which training draws a fresh cloud on every access",
    )
    parser.add_argument(
        "--strict", action="store_true", help="fail on any unreadable or degenerate file"
    )
    parser.add_argument(
        "--distinct",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="store identical geometry once and keep near-copies in one split (default: on "
        "for several sources, off for one)",
    )
    parser.add_argument(
        "--overwrite", action="store_true", help="replace an existing, non-empty --out folder"
    )


def run(args: argparse.Namespace) -> int:
    """Prepare the dataset and print a summary."""
    from pfnet.data.prepare import prepare_dataset

    given = list(args.source)
    if len(given) > 1:
        source = given
    else:
        source = None if given[0] == "procedural" else given[0]
    out = Path(args.out)
    if not args.overwrite and out.is_dir() and any(out.iterdir()):
        raise ConfigError(
            f"--out {args.out} already exists and is not empty (pass --overwrite to replace it)"
        )
    report = prepare_dataset(
        source,
        args.out,
        format="procedural" if source is None and args.format == "auto" else args.format,
        points=args.points,
        pool=args.pool,
        seed=args.seed,
        test_fraction=args.test_fraction,
        val_fraction=args.val_fraction,
        categories=args.categories,
        workers=args.workers,
        count=args.count,
        strict=args.strict,
        overwrite=args.overwrite,
        distinct=args.distinct,
    )
    print(report.summary())
    return 0
