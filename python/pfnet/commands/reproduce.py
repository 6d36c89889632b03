"""``pfnet reproduce``: the paper's comparisons re-run end to end on one data set.

The study of the paper's Tables 2, 4 and 5:

* the five generators of the ablation (PF-Net, PF-Net vanilla, MR-CMLP, CMLP, MLP) at 25 %
  missing, with identical data, epochs and schedule;
* PF-Net at 50 % and 75 % missing (the robustness study; M changes with the ratio);
* every such setting trained once per seed (0, 1, 2 by default), the tables giving the mean
  over the seeds and the spread between them;
* with ``--steps N 2N``, every setting also at each length in optimiser steps: the
  twice-the-steps test of convergence, the tables showing the shortest converged length.

Every run is predicted on the test split with the deterministic test protocol and scored on
the missing region and on the whole cloud. The results folder::

    OUT/data/                    the prepared data set (reused when present)
    OUT/runs/<run>/              config.json, log.jsonl, curves.png, best.pt, last.pt;
                                 <run> is <model>-<percent missing>-seed<seed>
                                 (<model>-<percent>-<N>steps-seed<seed> with --steps)
    OUT/runs/<run>/predictions/  predicted missing regions of the test split
    OUT/runs/<run>/eval-missing.json, eval-whole.json
    OUT/results.json             every run's record and the settings combined over seeds;
                                 everything below is built from this file
    OUT/results.md               the README section
    OUT/curves.png               validation curves of every run
    OUT/gallery.png              the same test shapes completed by each model

Running it again continues where it stopped: finished runs are kept, interrupted ones resume
from ``last.pt``. ``--publish DIR`` copies the small files (no data, checkpoints or
predictions) into ``DIR``; ``--readme README.md`` replaces the README's results section.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pfnet.errors import ConfigError, DataError
from pfnet.study.orchestrate import reproduce, rewrite_report
from pfnet.study.record import read_results
from pfnet.study.report import checked_report, publish, publish_readme, read_readme
from pfnet.study.runs import (
    BASE_RATIO,
    MAX_LENGTHS,
    MAX_RATIOS,
    MAX_SEEDS,
    STUDY_MODELS,
    STUDY_RATIOS,
    STUDY_SEEDS,
)
from pfnet.training.config import CHAMFER_KINDS, MAX_STEPS
from pfnet.viz.rendering import MAX_ROWS

# Trainings side by side on one device: a GPU's host has a few cores per run to give.
MAX_JOBS = 64


HELP = "Re-run the paper's comparisons: five models, three missing ratios, tables and figures."


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``pfnet reproduce``."""
    from pfnet.data import SWEETHOME3D_PATH

    parser.add_argument(
        "--out", type=Path, default=Path("pfnet-results"), help="results folder (pfnet-results)"
    )
    parser.add_argument(
        "--source",
        type=Path,
        default=None,
        help=f"models to build the data set from (default: {SWEETHOME3D_PATH})",
    )
    parser.add_argument(
        "--data", type=Path, default=None, help="use this prepared data set (pfnet prepare)"
    )
    parser.add_argument(
        "--preset",
        choices=("auto", "paper", "small"),
        default="auto",
        help="paper on a GPU, small on a CPU (default: auto)",
    )
    parser.add_argument(
        "--device", default="auto", help="auto (CUDA if available), cpu, cuda or cuda:N"
    )
    parser.add_argument("--models", nargs="+", default=list(STUDY_MODELS), metavar="MODEL")
    parser.add_argument(
        "--ratios", nargs="+", type=float, default=list(STUDY_RATIOS), metavar="RATIO"
    )
    parser.add_argument("--epochs", type=int, default=None, help="override the schedule's")
    parser.add_argument(
        "--steps",
        nargs="+",
        type=int,
        default=None,
        metavar="N",
        help="size every run in optimiser steps instead of epochs (the schedule's milestones "
        "become fractions of the run); several lengths train every setting at each, e.g. "
        "--steps 8000 16000 for the twice-the-steps test",
    )
    parser.add_argument(
        "--train-data",
        type=Path,
        default=None,
        help="train on this prepared data set's train split (e.g. every catalogue model, "
        "pfnet prepare --categories all); validation and test stay the study's data set",
    )
    parser.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="train up to this many runs side by side on the device, each in its own "
        "process (a GPU that one small run leaves idle); default 1",
    )
    parser.add_argument("--width", type=float, default=None, help="override the preset's")
    parser.add_argument("--batch-size", type=int, default=None, help="override the preset's")
    parser.add_argument(
        "--chamfer",
        choices=CHAMFER_KINDS,
        default=None,
        help="Chamfer terms of every run's loss: l2 (the paper, default) or l1 (see pfnet train)",
    )
    parser.add_argument(
        "--seeds",
        nargs="+",
        type=int,
        default=list(STUDY_SEEDS),
        metavar="SEED",
        help="train every setting once per seed (default: %(default)s)",
    )
    parser.add_argument(
        "--data-seed", type=int, default=0, help="seed of the data set's sampling and split (0)"
    )
    parser.add_argument("--gallery-count", type=int, default=5, help="shapes in the gallery")
    parser.add_argument(
        "--report-only",
        action="store_true",
        help="only rebuild the report, and the figures if the runs are there, from "
        "OUT/results.json",
    )
    parser.add_argument("--publish", type=Path, default=None, help="copy the small files here")
    parser.add_argument(
        "--readme", type=Path, default=None, help="replace this README's results section"
    )


def run(args: argparse.Namespace) -> int:
    """Run ``pfnet reproduce``."""
    out: Path = args.out
    unknown = [m for m in args.models if m not in STUDY_MODELS]
    if unknown:
        raise ConfigError(
            f"--models: unknown model(s) {', '.join(unknown)}; "
            f"choose from {', '.join(STUDY_MODELS)}"
        )
    bad = [r for r in args.ratios if not 0.0 < r < 1.0]
    if bad:
        raise ConfigError(f"--ratios must be in (0, 1); got {', '.join(map(str, bad))}")
    if len(set(args.ratios) | {BASE_RATIO}) > MAX_RATIOS:
        raise ConfigError(f"--ratios: at most {MAX_RATIOS} missing ratios, 0.25 included")
    if len(set(args.seeds)) > MAX_SEEDS:
        raise ConfigError(f"--seeds: at most {MAX_SEEDS} seeds")
    if args.steps is not None:
        if any(n < 1 for n in args.steps) or len(set(args.steps)) != len(args.steps):
            raise ConfigError("--steps: run lengths must be different integers >= 1")
        if len(args.steps) > MAX_LENGTHS:
            raise ConfigError(f"--steps: at most {MAX_LENGTHS} run lengths")
        if max(args.steps) > MAX_STEPS:
            raise ConfigError(f"--steps: at most {MAX_STEPS:,} steps a run")
        if args.epochs is not None:
            raise ConfigError("--epochs and --steps size the runs two ways; give one of them")
    if not 1 <= args.gallery_count <= MAX_ROWS:  # the rows a picture holds
        raise ConfigError(f"--gallery-count must be in [1, {MAX_ROWS}], got {args.gallery_count}")
    if not 1 <= args.jobs <= MAX_JOBS:
        raise ConfigError(f"--jobs must be between 1 and {MAX_JOBS}; got {args.jobs}")
    if args.readme is not None:
        if not args.readme.exists():
            raise ConfigError(f"--readme {args.readme} does not exist")
        if not args.readme.is_file():  # a folder, a pipe, a device
            raise ConfigError(f"--readme {args.readme} is not a regular file")
        read_readme(args.readme)  # before a study of hours, not after it
    if not args.report_only:  # the options of a study to run, not of a report to rebuild
        if args.data is None and args.source is not None and not args.source.exists():
            raise ConfigError(f"--source {args.source} does not exist")
        for flag, folder in (("--data", args.data), ("--train-data", args.train_data)):
            if folder is not None and not (folder / "manifest.json").is_file():
                raise DataError(f"{flag} {folder} is not a prepared data set (no manifest.json)")
    if args.report_only:
        try:  # a results.json edited by hand (or forged) must not end in a traceback
            results = read_results(out / "results.json")
            checked_report(results, out / "results.json")
        except DataError as err:
            raise DataError(f"--report-only: {err}") from None
        data_dir = args.data if args.data is not None else out / "data"
        rewrite_report(out, results, data_dir, args.gallery_count)
    else:
        from pfnet.data import SWEETHOME3D_PATH
        from pfnet.data.sources import pick_source
        from pfnet.inference.devices import inference_device

        device = inference_device(args.device)
        preset = args.preset if args.preset != "auto" else ("small" if device == "cpu" else "paper")
        source = None
        if args.data is None:
            source = pick_source(
                args.source,
                procedural=False,
                default=SWEETHOME3D_PATH,
                hint="sudo apt-get install sweethome3d-furniture",
                say=_say,
            )
        results = reproduce(
            out,
            source=source,
            data=args.data,
            preset=preset,
            device=device,
            seeds=list(dict.fromkeys(args.seeds)),
            data_seed=args.data_seed,
            models=list(dict.fromkeys(args.models)),
            ratios=list(dict.fromkeys(args.ratios)),
            overrides={
                "epochs": args.epochs,
                "width": args.width,
                "batch_size": args.batch_size,
                "chamfer": args.chamfer,
            },
            gallery_count=args.gallery_count,
            lengths=sorted(args.steps) if args.steps else None,
            train_data=args.train_data,
            jobs=args.jobs,
            log=_say,
            warn=_warn,
        )
    published = out
    if args.publish is not None:
        publish(out, args.publish)
        published = args.publish
    if args.readme is not None:
        publish_readme(args.readme, results, published)
        print(f"updated the results section of {args.readme}")
    print(f"results in {out}; report {published / 'results.md'}")
    sys.stdout.flush()
    return 0


def _say(line: str) -> None:
    """A line of the study's progress (from the runs' own processes too: a module's function)."""
    print(line, flush=True)


def _warn(line: str) -> None:
    """A run's error, from the process it failed in."""
    print(line, file=sys.stderr, flush=True)
