"""``pfnet complete``: complete your own partial point clouds with a trained model.

What is done to each input and which files are written: :mod:`pfnet.inference.completion`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pfnet.data.scan_frame import UP_AXES
from pfnet.errors import ConfigError
from pfnet.inference.completion import DEFAULT_MIRROR_FILL
from pfnet.inference.devices import DEVICE_HELP
from pfnet.inference.runtimes import RUNTIME_HELP, RUNTIMES
from pfnet.inference.shipped import CHECKPOINT_HELP

HELP = "Complete your own partial point clouds (PLY/XYZ/PTS/TXT/NPY/PCD) with a trained model."

EPILOG = """examples:
  pfnet complete scan.ply --out completed/              # y-up scan, the default shipped model
  pfnet complete lidar/*.xyz --up z --out completed/    # z-up scans (ROS, most scanners)
  pfnet complete scan.npy --checkpoint runs/mine/best.pt --out completed/

Each scan is normalised by its own centroid and radius (the scan frame) and turned y-up;
for each INPUT it writes OUT/<stem>_missing.ply (the predicted points) and
OUT/<stem>_completed.ply (the input, unchanged, then the predicted points). The
predicted points near the scan's own mirror images are swapped for those images
(--mirror-fill 0: the network's points only)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``pfnet complete``."""
    parser.add_argument(
        "inputs", nargs="+", type=Path, metavar="INPUT", help="partial clouds to complete"
    )
    parser.add_argument("--checkpoint", default=None, help=CHECKPOINT_HELP)
    parser.add_argument(
        "--up",
        choices=UP_AXES,
        default="y",
        help="the scans' up axis: y (default; SweetHome3D, OpenGL, the shipped models' "
        "data) or z (ROS, most scanners and LiDAR)",
    )
    parser.add_argument("--out", type=Path, required=True, help="folder for the PLY outputs")
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="replace output files in --out that pfnet did not write (a file of an earlier "
        "pfnet complete is always replaced)",
    )
    parser.add_argument(
        "--mirror-fill",
        type=float,
        default=DEFAULT_MIRROR_FILL,
        metavar="REACH",
        help="swap the predicted points near the scan's own mirror images (across its best "
        "vertical symmetry planes) for those images, which lie on a surface; REACH in the "
        f"scan's radii (default {DEFAULT_MIRROR_FILL}; 0: the network's points only)",
    )
    parser.add_argument("--batch-size", type=int, default=32, help="clouds per batch (default: 32)")
    parser.add_argument("--device", default="auto", help=DEVICE_HELP)
    parser.add_argument("--runtime", choices=RUNTIMES, default="auto", help=RUNTIME_HELP)


def run(args: argparse.Namespace) -> int:
    """Run ``pfnet complete``; exit 2 if some inputs could not be read (the rest are done)."""
    from pfnet.inference.completion import check_mirror_fill, check_outputs, complete_files
    from pfnet.inference.runtimes import load_generator

    if args.batch_size < 1:
        raise ConfigError(f"--batch-size must be at least 1, got {args.batch_size}")
    try:
        check_mirror_fill(args.mirror_fill)
    except ConfigError:
        raise ConfigError(
            f"--mirror-fill must be a distance >= 0 (0: off), got {args.mirror_fill}"
        ) from None
    if args.out.exists() and not args.out.is_dir():
        raise ConfigError(f"--out {args.out} is a file; name a folder for the outputs")
    inputs = check_outputs(args.inputs, args.out, overwrite=args.overwrite)
    loaded = load_generator(args.checkpoint, runtime=args.runtime, device=args.device)
    model, device = loaded.model, loaded.device
    frame = getattr(loaded.config, "frame", "shape")
    print(
        f"model {loaded.source} ({loaded.runtime}, trained in the {frame} frame); "
        f"scans {args.up}-up, normalised by their own centroid and radius; "
        + ("each turned back by the heading read from it; " if frame == "heading" else "")
        + (
            f"mirror fill within {args.mirror_fill:g}"
            if args.mirror_fill > 0
            else "the network's points only (--mirror-fill 0)"
        )
    )
    if frame == "shape":
        print(
            "note: this model was trained in the complete shape's frame (the paper's "
            "protocol), which a scan does not have; it completes scans worse than a "
            "scan-frame model (pfnet models)",
            file=sys.stderr,
        )
    done, failed = complete_files(
        model,
        inputs,
        args.out,
        up=args.up,
        frame=frame,
        batch_size=args.batch_size,
        device=device,
        on_skip=lambda err: print(f"skipped: {err}", file=sys.stderr),
        source=loaded.source,
        mirror_fill=args.mirror_fill,
    )
    if done:
        print(f"completed {len(done) // 2} of {len(inputs)} file(s); wrote:")
        for path in done:
            print(f"  {path}")
    else:
        print(f"completed none of {len(inputs)} file(s); nothing written")
    if failed:
        print(f"pfnet complete: {len(failed)} file(s) could not be read", file=sys.stderr)
        return 2
    return 0
