"""``pfnet render``: draw point cloud files into a PNG (see :mod:`pfnet.viz.rendering`)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from pfnet.errors import ConfigError

HELP = "Draw point clouds (partial grey, prediction yellow, ground truth blue) into a PNG."

ROLES = ("partial", "prediction", "ground-truth")
# --role -> the RenderSample field the FILE rows fill
_FIELDS = {"partial": "partial", "prediction": "prediction", "ground-truth": "ground_truth"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``pfnet render``."""
    parser.add_argument(
        "files",
        nargs="*",
        metavar="FILE",
        help="point cloud files (.npy .ply .xyz .pts .txt .pcd), one row each: a PLY file with "
        "its own colours (as pfnet complete writes) in them, any other coloured by --role",
    )
    parser.add_argument(
        "--sample",
        nargs=3,
        action="append",
        default=[],
        metavar=("PARTIAL", "PRED", "GT"),
        help="one row from a partial input, a prediction and a ground truth file "
        "('-' leaves one out); repeat for more rows",
    )
    parser.add_argument("--out", type=Path, default=None, help="PNG file to write")
    parser.add_argument(
        "--html",
        type=Path,
        default=None,
        help="interactive HTML file to write (rotatable, one toggle per layer; needs "
        "pip install plotly); with --out, both are written",
    )
    parser.add_argument(
        "--role",
        choices=ROLES,
        default=None,
        help="draw every FILE as this: partial grey, prediction yellow, ground-truth blue "
        "(default: a PLY file's own colours, e.g. x_completed.ply grey and yellow, titled by "
        "them; ground-truth for a file without colours)",
    )
    parser.add_argument("--views", type=int, default=2, help="view angles (default: 2)")
    parser.add_argument("--title", default=None, help="figure title")
    parser.add_argument("--point-size", type=float, default=2.0, help="marker size (default: 2)")


def run(args: argparse.Namespace) -> int:
    """Run ``pfnet render``."""
    from pfnet.io.clouds import read_point_cloud
    from pfnet.io.files import refuse_input_overwrite
    from pfnet.viz.rendering import MAX_POINT_SIZE, MAX_VIEWS, RenderSample, render_gallery

    if not args.files and not args.sample:
        raise ConfigError("give at least one FILE or --sample PARTIAL PRED GT")
    if args.out is None and args.html is None:
        raise ConfigError("give --out PICTURE.png, --html VIEWER.html or both")
    if args.out is not None and args.out.suffix.lower() != ".png":
        raise ConfigError(f"--out must be a .png file, got {args.out}")
    if args.html is not None and args.html.suffix.lower() != ".html":
        raise ConfigError(f"--html must be a .html file, got {args.html}")
    if not 1 <= args.views <= MAX_VIEWS:
        raise ConfigError(f"--views must be in [1, {MAX_VIEWS}], got {args.views}")
    if not (math.isfinite(args.point_size) and 0 < args.point_size <= MAX_POINT_SIZE):
        raise ConfigError(f"--point-size must be in (0, {MAX_POINT_SIZE:g}], got {args.point_size}")
    inputs = [*args.files, *(t for triple in args.sample for t in triple if t != "-")]
    outputs = [path for path in (args.out, args.html) if path is not None]
    refuse_input_overwrite(outputs, inputs, flag="--out/--html")
    samples = []
    for name in args.files:
        points = read_point_cloud(name)
        colors = None
        if args.role is None and Path(name).suffix.lower() == ".ply":
            from pfnet.io.formats.ply import read_ply_colors

            colors = read_ply_colors(Path(name))
        if colors is not None:
            samples.append(RenderSample(Path(name).name, cloud=points, cloud_colors=colors))
        else:
            samples.append(RenderSample(label=Path(name).name))
            setattr(samples[-1], _FIELDS[args.role or "ground-truth"], points)
    for triple in args.sample:
        if all(t == "-" for t in triple):
            raise ConfigError("--sample needs at least one file that is not '-'")
        clouds = [None if t == "-" else read_point_cloud(t) for t in triple]
        label = Path(next(t for t in triple if t != "-")).stem
        samples.append(RenderSample(label, *clouds))
    for out in outputs:
        path = render_gallery(
            out, samples, views=args.views, title=args.title, point_size=args.point_size
        )
        print(f"wrote {path} ({len(samples)} row(s))")
    return 0
