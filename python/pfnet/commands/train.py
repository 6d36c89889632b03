"""``pfnet train``: train PF-Net or a baseline on a prepared dataset.

The same command runs under ``torchrun --nproc_per_node N -m pfnet.cli train ...`` for
DistributedDataParallel training.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from pfnet.data.scan_frame import FRAMES
from pfnet.errors import ConfigError, DataError
from pfnet.models.registry import MODEL_NAMES
from pfnet.training.config import (
    CHAMFER_KINDS,
    LR_DECAYS,
    PRECISIONS,
    PRESETS,
    SCHEDULES,
    TRAIN_CROPS,
    TrainConfig,
    load_config,
    preset_config,
)

HELP = "Train PF-Net or a baseline on a prepared dataset (one process, or DDP under torchrun)."

# Command-line options that override a TrainConfig field of the same name.
OVERRIDES: dict[str, tuple[type, str]] = {
    "epochs": (int, "number of epochs"),
    "steps": (int, "size the run in optimiser steps instead (schedules become fractions of it)"),
    "warmup_steps": (int, "with --steps: linear learning-rate warm-up over this many steps"),
    "batch_size": (int, "clouds per step (per process under torchrun)"),
    "missing_ratio": (float, "fraction of points removed by the crop (default 0.25)"),
    "seed": (int, "seed of initialisation, shuffling and crops (default 0)"),
    "lr": (float, "Adam learning rate"),
    "weight_decay": (float, "Adam weight decay"),
    "width": (float, "network width multiplier (paper 1.0, small 0.25)"),
    "lr_step": (int, "StepLR period in epochs"),
    "lr_gamma": (float, "learning-rate factor at each StepLR period or --steps milestone"),
    "adversarial_weight": (float, "λ_adv of the joint loss (paper 0.05)"),
    "grad_clip": (
        float,
        "clip the generator's gradient to this L2 norm (paper preset 0: off, small 2)",
    ),
    "batchnorm_freeze": (
        float,
        "from this fraction of the run on, the generator's BatchNorm layers use their "
        "running statistics, frozen (paper preset 0: off, small 0.05)",
    ),
    "workers": (int, "data-loader worker processes, alive for the whole run"),
    "val_views": (
        int,
        "validate on every val shape cut at 1 or all 5 test viewpoints "
        "(paper preset 1, small preset 5)",
    ),
    "augment_scale": (float, "scale each axis of training clouds by U(1-s, 1+s) (default 0)"),
    "augment_jitter": (float, "std of Gaussian noise added to training clouds (default 0)"),
    "ema": (
        float,
        "keep an exponential moving average of the generator's weights with this decay "
        "(e.g. 0.999), which validation, best.pt and inference use (default 0: off)",
    ),
    "save_every": (
        str,
        "write last.pt every this long (10min, 90s, 1h) or N epochs (default 10min)",
    ),
    "init_from": (
        str,
        "fine-tune: start the generator from a best.pt, model file or shipped model's name "
        "(same model, width and points, or a PF-Net of a width that goes into --width a whole "
        "number of times, grown to the same function; fresh optimiser, schedule and "
        "discriminator)",
    ),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``pfnet train``."""
    parser.add_argument("--data", required=True, type=Path, help="dataset folder (pfnet prepare)")
    parser.add_argument(
        "--val-data",
        type=Path,
        default=None,
        help="validate on this data set's val split instead (default: --data's)",
    )
    parser.add_argument("--out", required=True, type=Path, help="run folder to write")
    parser.add_argument("--model", choices=MODEL_NAMES, help="generator (default: pfnet)")
    parser.add_argument("--preset", choices=tuple(PRESETS), help="base configuration (paper)")
    parser.add_argument("--config", type=Path, help="TOML file of config keys over the preset")
    parser.add_argument(
        "--crop",
        choices=TRAIN_CROPS,
        help="training crop (default viewpoint); turned: a viewpoint turned by a random angle "
        "about the up axis, the shape keeping its heading (for --frame heading); scanner: what "
        "a depth camera sees from a random position, validated on the scanner test protocol "
        "(use --missing-ratio 0.5)",
    )
    parser.add_argument(
        "--schedule",
        choices=SCHEDULES,
        help="a run in epochs: fixed, StepLR every --lr-step epochs (the paper preset), or "
        "run, the learning rate x --lr-gamma at 50 %% and 75 %% of the epochs (the small "
        "preset: any --epochs gets a schedule sized to it)",
    )
    parser.add_argument(
        "--lr-decay",
        choices=LR_DECAYS,
        dest="lr_decay",
        help="how a schedule sized to the run (--steps, or --schedule run) lowers the learning "
        "rate: step, x --lr-gamma at each milestone (default), or cosine, along a half cosine "
        "to the same final rate at the end of the run",
    )
    parser.add_argument(
        "--frame",
        choices=FRAMES,
        help="frame of the network's input: scan, the partial's own centroid and radius (what "
        "pfnet complete gives a model; the small preset's default); aligned, that frame "
        "turned about the up axis to the partial's main horizontal axis; aligned-end, the same "
        "pointing to the axis's sparser end, where a cut usually is; aligned-rim, the same "
        "given the quarter turn that brings the cut's rim (where points have neighbours on "
        "one side only) nearest +x; rim, the scan frame turned so that the rim lies at +x; "
        "heading, the scan "
        "frame in the data set's own heading, validated on turned partials read back by the "
        "shipped heading reader (train with --crop turned); or shape, the complete shape's "
        "(the paper's protocol; the paper preset's default)",
    )
    parser.add_argument(
        "--chamfer",
        choices=CHAMFER_KINDS,
        help="Chamfer terms of the loss: l2, mean squared distances (the paper, default), "
        "or l1, mean distances (better on the small SweetHome3D data set; README)",
    )
    for name, (kind, text) in OVERRIDES.items():
        flag = "--" + name.replace("_", "-")
        parser.add_argument(flag, type=kind, dest=name, metavar=name.upper(), help=text)
    parser.add_argument(
        "--precision",
        choices=PRECISIONS,
        help="fp32 (exact, default) or bf16 autocast of the networks (Chamfer stays float32)",
    )
    parser.add_argument(
        "--augment-rotate",
        dest="augment_rotate",
        action="store_const",
        const=True,
        help="rotate training clouds by a random angle about the data set's up axis",
    )
    parser.add_argument(
        "--compile",
        action="store_const",
        const=True,
        help="run the networks through torch.compile (slow start, faster steps on a GPU)",
    )
    parser.add_argument(
        "--device", default="auto", help="auto (CUDA if available), cpu, cuda or cuda:N"
    )
    parser.add_argument(
        "--threads",
        type=_threads,
        default="auto",
        help="torch threads of each process on the CPU: N, or auto (default): the cores not "
        "busy with other work when the run starts, shared among torchrun's processes "
        "(torch's own default, one per core, is up to 1.7x slower on a shared machine); "
        "OMP_NUM_THREADS, when set, decides instead",
    )
    parser.add_argument(
        "--resume",
        action="store_true",
        help="continue the run in --out from its last.pt (only --epochs, --workers, "
        "--precision, --compile and --save-every may change)",
    )


def build_config(args: argparse.Namespace) -> TrainConfig:
    """The run's configuration: preset, then ``--config`` file, then explicit options.

    With ``--resume`` the base is the run's stored ``config.json`` instead.
    """
    if args.steps is not None and args.epochs is not None:
        raise ConfigError("--epochs and --steps size the run two ways; give one of them")
    names = (
        "model",
        "schedule",
        "lr_decay",
        "crop",
        "chamfer",
        "frame",
        "precision",
        "compile",
        "augment_rotate",
        *OVERRIDES,
    )
    overrides = {name: getattr(args, name) for name in names}
    overrides = {k: v for k, v in overrides.items() if v is not None}
    if args.resume:
        if args.preset or args.config:
            raise ConfigError(
                "--preset and --config cannot be combined with --resume "
                "(the run's configuration is stored in it)"
            )
        stored = args.out / "config.json"
        if not stored.is_file():
            raise DataError(f"cannot resume: {stored} does not exist")
        try:
            data = json.loads(stored.read_text())
        except (OSError, ValueError, RecursionError) as err:  # RecursionError: forged nesting
            raise DataError(f"cannot resume: {stored} is unreadable: {str(err)[:200]}") from None
        base = TrainConfig.from_dict(data, source=str(stored))
    elif args.config is not None:
        base = load_config(args.config, preset=args.preset)
        if base.steps is not None and args.epochs is not None and args.steps is None:
            raise ConfigError(
                f"--epochs with a config file that sizes the run in steps ({args.config}); "
                "give --steps instead, or remove steps from the file"
            )
    else:
        base = preset_config(args.preset or "paper")
    return base.replace(**overrides)


# Said when no --preset (nor a config file) chooses one: the default is sized for a GPU.
DEFAULT_PRESET_NOTE = (
    "no --preset given: training the `paper` preset (the paper's full-width network, batch "
    "36: sized for a GPU, about 8.7 s a step on a 2-core CPU); --preset small trains on a CPU"
)


def _threads(text: str) -> str | int:
    if text == "auto":
        return text
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be auto or a positive whole number, got {text!r}")
    return value


def torch_threads(threads: str | int) -> int | None:
    """The torch threads ``--threads`` asks for, or ``None`` to leave torch's setting
    (``OMP_NUM_THREADS`` given with ``auto``)."""
    import os

    from pfnet.processes import idle_cpus

    if threads != "auto":
        return int(threads)
    if os.environ.get("OMP_NUM_THREADS"):
        return None
    local = int(os.environ.get("LOCAL_WORLD_SIZE", "1") or 1)  # torchrun's processes here
    return max(1, idle_cpus() // max(1, local))


def run(args: argparse.Namespace) -> int:
    """Train; print a one-line summary. Exit code 130 after Ctrl-C (the run is saved)."""
    config = build_config(args)
    if args.out.exists() and not args.out.is_dir():
        raise ConfigError(f"--out {args.out} exists and is not a folder")
    # --out equal to --data gets the shared check's message: outputs apart from the inputs
    other = (args.out / "manifest.json").is_file() or (args.out / "predictions.json").is_file()
    if other and args.out.resolve() != args.data.resolve():
        from pfnet.io.files import other_kind

        raise ConfigError(f"--out {args.out} is {other_kind(args.out)}; name a folder for the run")
    if not args.resume and (args.out / "last.pt").exists():
        raise ConfigError(
            f"{args.out} already holds a run (last.pt); pass --resume to continue it "
            "or choose another --out"
        )
    if args.preset is None and args.config is None and not args.resume:
        print(f"pfnet train: note: {DEFAULT_PRESET_NOTE}", file=sys.stderr)
    from pfnet.training.loop import train
    from pfnet.training.signals import STOP_NOTICE

    threads = torch_threads(args.threads)
    if threads is not None:
        import torch

        from pfnet.processes import usable_cpus

        torch.set_num_threads(threads)
        if args.threads == "auto" and threads < usable_cpus():
            print(
                f"pfnet train: note: {threads} torch thread(s) per process: other work keeps "
                f"the rest of the {usable_cpus()} cores busy (--threads N to choose)",
                file=sys.stderr,
            )
    summary = train(
        config,
        args.data,
        args.out,
        device=args.device,
        resume=args.resume,
        val_data=args.val_data,
        notes=lambda note: print(f"pfnet train: note: {note}", file=sys.stderr),
        say=lambda line: print(line, file=sys.stderr),
        on_stop=lambda: print(f"\npfnet train: {STOP_NOTICE}", file=sys.stderr),
    )
    if summary["world_size"] > 1:
        import os

        if os.environ.get("RANK", "0") != "0":
            return 130 if summary["interrupted"] else 0
    if summary["interrupted"]:
        print(
            f"pfnet train: saved {summary['last']} at epoch {summary['epochs'] + 1}, "
            f"batch {summary['batches_done']}; continue with --resume",
            file=sys.stderr,
        )
    best = summary["best_val_cd_l2"]
    best_text = f"{best:.4g}" if best is not None else "n/a"
    print(
        f"trained {config.model} for {summary['epochs']} epoch(s) on "
        f"{summary['world_size']} process(es); best val CD-L2 x1000 {best_text} "
        f"(epoch {summary['best_epoch']}); run in {args.out}",
        file=sys.stdout,
    )
    return 130 if summary["interrupted"] else 0
