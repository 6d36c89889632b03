"""``pfnet export``: write a trained generator as an ONNX file (:mod:`pfnet.inference.onnx_export`).

The file runs on ONNX Runtime without PyTorch: ``pfnet complete --checkpoint model.onnx``
(or ``predict``). Exporting needs PyTorch, ``onnx`` and ``onnxscript``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from pfnet.errors import ConfigError
from pfnet.inference.shipped import CHECKPOINT_HELP

HELP = "Export a trained generator to ONNX, to complete scans with ONNX Runtime (no PyTorch)."
EXPORT_EXTRA = "the [export] extra of pfnet-completion"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``pfnet export``."""
    parser.add_argument("--checkpoint", default=None, help=CHECKPOINT_HELP)
    parser.add_argument("--out", type=Path, required=True, help="the .onnx file to write")
    parser.add_argument(
        "--no-check",
        action="store_true",
        help="skip running the file on ONNX Runtime against PyTorch",
    )


def run(args: argparse.Namespace) -> int:
    """Run ``pfnet export``."""
    from pfnet.errors import MissingDependency
    from pfnet.inference.runtimes import has_module
    from pfnet.inference.shipped import resolve_checkpoint
    from pfnet.io.files import refuse_input_overwrite

    if args.out.suffix.lower() != ".onnx":
        raise ConfigError(f"--out must be a .onnx file, got {args.out}")
    source = resolve_checkpoint(args.checkpoint)
    refuse_input_overwrite([args.out], [source], flag="--out")
    missing = [name for name in ("torch", "onnx", "onnxscript") if not has_module(name)]
    if missing:
        raise MissingDependency(
            f"export needs {', '.join(missing)}: pip install {' '.join(missing)} ({EXPORT_EXTRA})"
        )
    from pfnet.inference.onnx_export import TOLERANCE, export_onnx

    result = export_onnx(source, args.out, check=not args.no_check)
    meta = result["metadata"]
    print(
        f"wrote {result['path']} ({result['size_mb']:.1f} MB, {meta['model']}: "
        f"{meta['n_points']} points, predicts {meta['n_missing']})"
    )
    if result["max_abs_diff"] is not None:
        print(
            f"checked on ONNX Runtime: max abs difference from PyTorch "
            f"{result['max_abs_diff']:.2g} (tolerance {TOLERANCE:g})"
        )
    print(f"complete scans with it: pfnet complete SCAN.ply --checkpoint {args.out} --out OUT")
    return 0
