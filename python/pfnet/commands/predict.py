"""``pfnet predict``: run a trained model over a data set split with the test protocol.

Sample *i* of the split loses the ``round(r·N)`` points nearest ``VIEWPOINTS[i % 5]``
(:func:`pfnet.data.test_protocol_crop`, DESIGN.md §3); the model predicts the missing region
from the rest. Output, ready for ``pfnet evaluate``::

    PRED/<category>/<name>.npy    float32 (M, 3) predicted missing region, one per sample
    PRED/predictions.json         checkpoint, data, split, protocol and model

The run is deterministic: no random numbers are drawn, and the model is in eval mode.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pfnet.errors import ConfigError
from pfnet.evaluation.protocols import Protocol, get_protocol
from pfnet.inference.benchmarks import predict_benchmark
from pfnet.inference.devices import DEVICE_HELP
from pfnet.inference.predict import predict_split
from pfnet.inference.runtimes import RUNTIME_HELP, RUNTIMES
from pfnet.inference.shipped import CHECKPOINT_HELP

HELP = "Predict the missing region of every sample of a data set split (test protocol)."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``pfnet predict``."""
    parser.add_argument("--checkpoint", default=None, help=CHECKPOINT_HELP)
    parser.add_argument("--data", type=Path, required=True, help="prepared data set folder")
    parser.add_argument("--split", default="test", help="split to predict (default: test)")
    parser.add_argument(
        "--protocol",
        choices=("pfnet", "pcn", "shapenet55", "shapenet34", "kitti"),
        default="pfnet",
        help="pfnet (default): PF-Net's crop, the missing region is written; pcn: the given "
        "partial scans; shapenet55 (= shapenet34): PoinTr's 8 viewpoints; kitti: the KITTI "
        "cars, pose-normalised by their boxes; the last three write whole completions for "
        "evaluate --protocol",
    )
    parser.add_argument(
        "--missing-ratio",
        type=float,
        default=None,
        help="fraction of points the test crop removes (default: the checkpoint's; "
        "shapenet55: 0.25, 0.5 or 0.75, default 0.25)",
    )
    parser.add_argument("--out", type=Path, required=True, help="prediction folder to write")
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the predictions of another run (data set, split or protocol) in --out",
    )
    parser.add_argument("--batch-size", type=int, default=32, help="clouds per batch (default: 32)")
    parser.add_argument("--device", default="auto", help=DEVICE_HELP)
    parser.add_argument("--runtime", choices=RUNTIMES, default="auto", help=RUNTIME_HELP)
    parser.add_argument(
        "--gallery",
        type=Path,
        default=None,
        help="also render some predictions into a PNG (or, .html, an interactive viewer)",
    )
    parser.add_argument(
        "--gallery-count", type=int, default=None, help="samples in the gallery (default: 8)"
    )


def run(args: argparse.Namespace) -> int:
    """Run ``pfnet predict``."""
    if args.batch_size < 1:
        raise ConfigError(f"--batch-size must be at least 1, got {args.batch_size}")
    if args.missing_ratio is not None and not 0.0 < args.missing_ratio < 1.0:
        raise ConfigError(f"--missing-ratio must be in (0, 1), got {args.missing_ratio}")
    if args.out.exists() and not args.out.is_dir():
        raise ConfigError(f"--out {args.out} is a file; name a folder for the predictions")
    # Never mix predictions into a data set (--out equal to --data gets the shared check's
    # message, which says why: outputs apart from the inputs).
    if (args.out / "manifest.json").exists() and args.out.resolve() != args.data.resolve():
        raise ConfigError(f"--out {args.out} is a prepared data set; name another folder")
    if (args.out / "last.pt").is_file() or (args.out / "best.pt").is_file():
        raise ConfigError(f"--out {args.out} is a training run; name another folder")
    _check_gallery(args)
    from pfnet.evaluation.prediction_folder import release_folders
    from pfnet.io.locks import reading

    # the data set is held while it is read: a prepare --overwrite meanwhile is refused
    try:
        with reading(args.data, "predicting from"):
            return _run(args)
    finally:  # an interrupted run lets go of its --out too (main may be called again)
        release_folders()


def _run(args: argparse.Namespace) -> int:
    if args.protocol != "pfnet":
        return _run_benchmark(args)
    info = predict_split(
        args.checkpoint,
        args.data,
        args.out,
        split=args.split,
        missing_ratio=args.missing_ratio,
        batch_size=args.batch_size,
        device=args.device,
        runtime=args.runtime,
        overwrite=args.overwrite,
    )
    ratio = info["protocol"]["missing_ratio"]
    print(
        f"wrote {info['n_samples']} predictions of {info['model']['n_predicted']} points to "
        f"{args.out}/<category>/<name>.npy ({info['split']} split, {ratio:.0%} missing)"
    )
    if args.gallery is not None:
        from pfnet.viz.gallery import render_prediction_gallery

        path = render_prediction_gallery(
            args.gallery,
            args.out,
            args.data,
            split=args.split,
            missing_ratio=ratio,
            count=args.gallery_count,
        )
        print(f"wrote {path}")
    print(f"score it: pfnet evaluate {args.out} --data {args.data} --missing-ratio {ratio:g}")
    return 0


def _run_benchmark(args: argparse.Namespace) -> int:
    """``pfnet predict --protocol pcn|shapenet55|kitti``: whole completions of the benchmark's
    inputs; exit 2 if some shapes were skipped (the rest are written)."""
    _check_benchmark_ratio(get_protocol(args.protocol), args.missing_ratio)
    info = predict_benchmark(
        args.checkpoint,
        args.data,
        args.out,
        args.protocol,
        split=args.split,
        missing_ratio=args.missing_ratio,
        batch_size=args.batch_size,
        device=args.device,
        runtime=args.runtime,
        overwrite=args.overwrite,
    )
    ratio = info["protocol"]["missing_ratio"]
    shown = "" if ratio is None else f", {ratio:.0%} missing"
    print(
        f"wrote {info['n_samples']} completions (input + {info['model']['n_predicted']} "
        f"predicted points) to {args.out} ({info['split']} split, protocol "
        f"{info['protocol']['name']}{shown})"
    )
    name = info["protocol"]["name"]
    more = " --references CARS" if name == "kitti" else ""
    if args.gallery is not None:
        from pfnet.evaluation.scoring import find_prediction_files
        from pfnet.viz.gallery import render_benchmark_gallery

        path = render_benchmark_gallery(
            args.gallery,
            args.out,
            args.data,
            name,
            keys=sorted(find_prediction_files(args.out)),
            count=args.gallery_count,
            split=args.split,
            missing_ratio=ratio,
        )
        print(f"wrote {path}")
    print(f"score it: pfnet evaluate {args.out} --data {args.data} --protocol {name}{more}")
    n_skipped = info.get("n_skipped", 0)
    if n_skipped:
        for reason in info["skipped"]:
            print(f"skipped: {reason}", file=sys.stderr)
        if n_skipped > len(info["skipped"]):
            print(f"skipped: and {n_skipped - len(info['skipped'])} more", file=sys.stderr)
        print(f"pfnet predict: {n_skipped} shape(s) could not be completed", file=sys.stderr)
        return 2
    return 0


def _check_gallery(args: argparse.Namespace) -> None:
    """Check ``--gallery`` before predicting: never over the data or the checkpoint."""
    from pfnet.viz.gallery import check_gallery_options

    args.gallery_count = check_gallery_options(args.gallery, args.gallery_count)
    if args.gallery is None:
        return
    from pfnet.data.format import split_categories
    from pfnet.inference.shipped import resolve_checkpoint
    from pfnet.io.files import check_report_path

    inputs = [args.data, resolve_checkpoint(args.checkpoint)]
    categories = split_categories(args.data, args.split)  # the folders to come
    check_report_path(args.gallery, args.out, inputs, flag="--gallery", categories=categories)


def _check_benchmark_ratio(chosen: Protocol, ratio: float | None) -> None:
    """Refuse a ``--missing-ratio`` that is not finite, not in (0, 1) or not the protocol's."""
    if ratio is None:
        return
    if not 0.0 < ratio < 1.0:  # also false for NaN
        raise ConfigError(f"--missing-ratio must be in (0, 1), got {ratio}")
    if chosen.ratios and not any(abs(ratio - r) <= 1e-9 for r in chosen.ratios):
        listed = ", ".join(f"{r:g}" for r in chosen.ratios)
        raise ConfigError(
            f"--missing-ratio of the {chosen.name} protocol is one of {listed}, got {ratio:g}"
        )
