"""``pfnet demo``: the whole pipeline on real data in a few minutes on a CPU.

What it does and where it writes: :mod:`pfnet.study.demo`.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from pfnet.data import SWEETHOME3D_PATH
from pfnet.errors import ConfigError

HELP = "Run the whole pipeline on real furniture models: prepare, train, predict, evaluate."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``pfnet demo``."""
    parser.add_argument(
        "--out", type=Path, default=Path("pfnet-demo"), help="output folder (default: pfnet-demo)"
    )
    parser.add_argument(
        "--minutes",
        type=float,
        default=5.0,
        help="training time budget in minutes (default: 5)",
    )
    parser.add_argument(
        "--epochs",
        type=int,
        default=None,
        help="train exactly this many epochs instead of filling --minutes",
    )
    parser.add_argument(
        "--source",
        type=Path,
        default=None,
        help=f"models to build the data set from (default: {SWEETHOME3D_PATH})",
    )
    parser.add_argument(
        "--procedural", action="store_true", help="use procedural shapes, not real models"
    )
    parser.add_argument(
        "--points", type=int, default=2048, help="points per shape (default: 2048, as the paper)"
    )
    parser.add_argument(
        "--count",
        type=int,
        default=None,
        help="shapes per category of procedural data (default: 100)",
    )
    parser.add_argument("--device", default="cpu", help="auto, cpu, cuda or cuda:N (default: cpu)")
    parser.add_argument("--seed", type=int, default=0, help="seed of data and training")
    parser.add_argument(
        "--gallery-count", type=int, default=6, help="samples in the gallery (default: 6)"
    )


def run(args: argparse.Namespace) -> int:
    """Run ``pfnet demo``."""
    from pfnet.study.demo import MAX_MINUTES, run_demo
    from pfnet.viz.rendering import MAX_ROWS

    if not (math.isfinite(args.minutes) and 0 < args.minutes <= MAX_MINUTES):
        raise ConfigError(f"--minutes must be positive and at most a week, got {args.minutes}")
    if args.epochs is not None and args.epochs < 1:
        raise ConfigError(f"--epochs must be at least 1, got {args.epochs}")
    if not 1 <= args.gallery_count <= MAX_ROWS:  # before the demo's work, not after it
        raise ConfigError(f"--gallery-count must be in [1, {MAX_ROWS}], got {args.gallery_count}")
    if args.procedural and args.source is not None:
        raise ConfigError("--procedural and --source name two sources; give one of them")
    if not 0 <= args.seed < 2**63:  # before the data set is prepared with it, not after
        raise ConfigError(f"--seed must be an integer in [0, 2**63), got {str(args.seed)[:40]}")
    if args.source is not None and not args.source.exists():
        raise ConfigError(f"--source {args.source} does not exist")
    result = run_demo(
        args.out,
        minutes=args.minutes,
        epochs=args.epochs,
        source=args.source,
        procedural=args.procedural,
        points=args.points,
        count=args.count,
        device=args.device,
        seed=args.seed,
        gallery_count=args.gallery_count,
        say=lambda line: print(line, flush=True),
    )
    _print_summary(result)
    return 0


def _print_summary(result) -> None:
    """Where everything is, and what to run next."""
    from pfnet.evaluation.scoring import SCALE

    mean, shipped = result.mean, result.shipped_mean
    print(f"\ndone in {result.minutes:.1f} min. Everything is in {result.out}:")
    print(f"  data set      {result.data_dir}  ({result.source})")
    print(f"  checkpoint    {result.checkpoint}")
    print(f"  predictions   {result.pred_dir}/<category>/<name>.npy")
    print(
        f"  metrics       {result.metrics}  (mean Pred→GT {mean['pred_to_gt']:.3f}, "
        f"GT→Pred {mean['gt_to_pred']:.3f}, ×{SCALE})"
    )
    if shipped is not None:
        print(
            f"  shipped model {result.shipped_metrics}  (mean Pred→GT "
            f"{shipped['pred_to_gt']:.3f}, GT→Pred {shipped['gt_to_pred']:.3f})"
        )
    print(f"  gallery       {result.gallery}")
    for licence in result.licences:
        # One line per catalogue; the per-shape creators are in the data set's manifest.json.
        print(
            f"  data credit   {licence.get('catalogue')} ({licence.get('license')}), "
            f"{len(licence.get('creators', []))} creators, "
            f"see {result.data_dir / 'manifest.json'}"
        )
    print("next: pfnet complete your_scan.ply --out completed/   (the shipped model)")
    print(f"      pfnet complete your_scan.ply --checkpoint {result.checkpoint} --out completed/")
