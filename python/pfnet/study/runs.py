"""The study's runs: which settings, their configurations, training and scoring one run."""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pfnet.errors import ConfigError, DataError
from pfnet.models.registry import PAPER_MODELS
from pfnet.study.aggregate import _summary

# The ablation's generators: every registered model, in the paper's order (PF-Net first).
STUDY_MODELS = PAPER_MODELS


BASE_RATIO = 0.25


STUDY_RATIOS = (0.25, 0.5, 0.75)


# Training seeds: every setting is trained once per seed, so the tables can say how much of a
# difference between two models is larger than the spread between seeds of one model.
STUDY_SEEDS = (0, 1, 2)


# The largest study pfnet runs, and so the largest results.json it reads back: up to ten
# times the default seeds, three times the default ratios and four run lengths (--steps).
# With every model that is (5 + 9 - 1) settings × 30 seeds × 4 lengths = 1,560 runs, a
# record of some MB.
MAX_SEEDS = 10 * len(STUDY_SEEDS)


MAX_RATIOS = 3 * len(STUDY_RATIOS)


MAX_LENGTHS = 4


MAX_RUNS = (len(STUDY_MODELS) + MAX_RATIOS - 1) * MAX_SEEDS * MAX_LENGTHS


# The schedule of each preset in the study. ``paper`` is the authors' (200 epochs, StepLR 40,
# α stepping at epochs 30 and 80). ``small`` keeps the authors' 200 epochs and StepLR 40 (the
# learning rate ends at 1e-3 · 0.2⁴ = 1.6e-6) with α stepping earlier, at 20 and 50. At 120
# epochs the PF-Net runs had levelled off on SweetHome3D but the three baselines were still
# improving by about 4 % in their last 30 epochs; the authors' length settles every model.
STUDY_SCHEDULES: dict[str, dict[str, Any]] = {
    "paper": {},
    # The paper's tables: its protocol (the complete shape's frame) and StepLR schedule, not
    # the small preset's scan frame and run-sized schedule.
    "small": {
        "epochs": 200,
        "lr_step": 40,
        "alpha_schedule": ((0, 0.01), (20, 0.05), (50, 0.1)),
        "frame": "shape",
        "schedule": "fixed",
        # the paper's val protocol, one cut per shape, as every published run of the study
        "val_views": 1,
        # the paper's batch statistics and unclipped gradients, as the published runs
        "batchnorm_freeze": 0.0,
        "grad_clip": 0.0,
        # the rate every published run trained with (the small preset's is half of it now)
        "lr": 1e-3,
    },
}


# A run counts as trained to a plateau when the best validation CD-L2 of its last quarter of
# epochs improves on the best before it by less than this fraction.
PLATEAU_TOLERANCE = 0.02


# The twice-the-steps test of a study sized in steps (``--steps N 2N``): a setting counts as
# converged at N steps when its run of 2N steps is not better on validation (best CD-L2) by
# more than this fraction. A learning rate decayed to nothing flattens any curve, so the
# plateau of one run's curve is not enough; a longer run with the same schedule is.
CONVERGENCE_TOLERANCE = 0.03


PUBLISHED_RUN_FILES = ("config.json", "log.jsonl", "eval-missing.json", "eval-whole.json")


@dataclass(frozen=True)
class StudyRun:
    """One training run of the study.

    Attributes:
        model: Generator name.
        missing_ratio: Fraction of each cloud removed by the crop.
        seed: Training seed (initialisation, shuffling, crops).
        steps: Length of the run in optimiser steps (``None``: the schedule's epochs).
    """

    model: str
    missing_ratio: float
    seed: int = 0
    steps: int | None = None

    @property
    def setting(self) -> str:
        """The model, ratio and length shared by the seeds of one setting, e.g. ``pfnet-25``
        (or ``pfnet-25-8000steps`` in a study sized in steps)."""
        name = f"{self.model}-{round(self.missing_ratio * 100)}"
        return name if self.steps is None else f"{name}-{self.steps}steps"

    @property
    def name(self) -> str:
        """Folder name, e.g. ``pfnet-25-seed0``."""
        return f"{self.setting}-seed{self.seed}"


def study_runs(
    models: Sequence[str],
    ratios: Sequence[float],
    seeds: Sequence[int] = (0,),
    lengths: Sequence[int | None] = (None,),
) -> list[StudyRun]:
    """The runs, seed by seed and length by length: every model at 25 % missing, then PF-Net
    at the other ratios.

    Seeds come outermost, so a study stopped early has whole seeds rather than whole models.
    ``lengths`` are the run lengths in steps (``None``: the schedule's epochs); a study sized
    in steps trains every setting at each length, for the twice-the-steps test.
    """
    runs = []
    for seed in seeds:
        for steps in lengths:
            runs += [StudyRun(m, BASE_RATIO, seed, steps) for m in models]
            if "pfnet" in models:
                runs += [StudyRun("pfnet", r, seed, steps) for r in ratios if r != BASE_RATIO]
    return runs


def completed_epochs(run_dir: Path) -> int:
    """Epochs finished by the run in ``run_dir`` (0 if it has not started)."""
    return len(read_log(run_dir)) - 1 if (run_dir / "log.jsonl").is_file() else 0


def read_log(run_dir: Path) -> list[dict[str, Any]]:
    """The rows of ``run_dir/log.jsonl`` (row 0: the untrained model)."""
    path = run_dir / "log.jsonl"
    try:
        rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    except (OSError, ValueError, RecursionError) as err:
        raise DataError(f"cannot read the training log {path}: {str(err)[:200]}") from None
    if not all(isinstance(row, dict) for row in rows):
        raise DataError(f"cannot read the training log {path}: rows must be JSON objects")
    return rows


def plateau(curve: Sequence[float], tolerance: float = PLATEAU_TOLERANCE) -> dict[str, Any]:
    """How much the last quarter of a validation curve still improved.

    Args:
        curve: Validation metric after each epoch (lower is better), epoch 1 first.
        tolerance: Largest relative gain that still counts as levelled off.

    Returns:
        ``window`` (epochs in the last quarter), ``gain`` (relative improvement of the best
        value in the window over the best before it; negative when it got worse) and
        ``levelled`` (``gain < tolerance``). ``gain`` is None for curves under 4 epochs.
    """
    values = [float(v) for v in curve]
    window = len(values) // 4
    if window < 1:
        return {"window": window, "gain": None, "levelled": False}
    before, last = min(values[:-window]), min(values[-window:])
    gain = (before - last) / before if before > 0 else 0.0
    return {"window": window, "gain": gain, "levelled": gain < tolerance}


def study_config(preset: str, **overrides: Any) -> Any:
    """The configuration shared by every run: the preset with the study's schedule.

    Each run then sets its own model, missing ratio and seed.
    """
    from pfnet.training.config import preset_config

    changes = dict(STUDY_SCHEDULES.get(preset, {}))
    changes.update({k: v for k, v in overrides.items() if v is not None})
    return preset_config(preset).replace(**changes)


def run_config(run: StudyRun, base: Any) -> Any:
    """The configuration of ``run``: the study's shared one with its model, ratio, seed and
    length."""
    config = base.replace(model=run.model, missing_ratio=run.missing_ratio, seed=run.seed)
    return config if run.steps is None else config.replace(steps=run.steps)


def _finished(run_dir: Path, config: Any) -> bool:
    """Whether the log of ``run_dir`` reaches the end of ``config``'s run."""
    if config.steps is None:
        return completed_epochs(run_dir) >= config.epochs
    rows = read_log(run_dir) if (run_dir / "log.jsonl").is_file() else []
    return bool(rows) and isinstance(rows[-1].get("step"), int) and rows[-1]["step"] >= config.steps


def train_run(
    run: StudyRun,
    base: Any,
    data_dir: Path,
    run_dir: Path,
    device: str,
    log: Callable,
    train_data: Path | None = None,
    progress: bool | None = None,
) -> None:
    """Train ``run`` to the end of its schedule, resuming or skipping what an earlier call did.

    With ``train_data``, the run trains on that data set's train split and validates on
    ``data_dir``'s val split (as ``pfnet train --val-data``).
    """
    from pfnet.training import train
    from pfnet.training.config import RESUMABLE_FIELDS, TrainConfig
    from pfnet.training.signals import STOP_NOTICE

    config = run_config(run, base)
    options = {} if train_data is None else {"val_data": data_dir}
    options |= {"say": log, "on_stop": lambda: log(STOP_NOTICE)}  # the training's lines
    data_dir = data_dir if train_data is None else train_data
    length = f"{config.epochs} epochs" if config.steps is None else f"{config.steps} steps"
    done = completed_epochs(run_dir)
    if (run_dir / "last.pt").is_file():
        try:
            stored = json.loads((run_dir / "config.json").read_text())
            if not isinstance(stored, dict):
                raise ValueError("not a JSON object")
        except (OSError, ValueError, RecursionError) as err:
            raise DataError(f"{run_dir / 'config.json'} is unreadable: {str(err)[:200]}") from None
        # Only the length of the run may change (n_points is filled in from the data). Read
        # through TrainConfig: a key added since the run started takes its default, which
        # is what the run trains with.
        stored = TrainConfig.from_dict(stored, source=str(run_dir / "config.json")).to_dict()
        free = (*RESUMABLE_FIELDS, "n_points")
        wanted = {k: v for k, v in config.to_dict().items() if k not in free}
        if {k: v for k, v in stored.items() if k not in free} != wanted:
            raise ConfigError(
                f"{run_dir} holds a run with another configuration; delete it or choose "
                "another results folder"
            )
        from pfnet.inference.checkpoint import read_checkpoint
        from pfnet.training.resume import data_identity

        state = read_checkpoint(run_dir / "last.pt", "cpu")
        stored, current = state.get("data") or {}, data_identity(data_dir)
        if (
            stored.get("kind") == current["kind"]
            and stored.get("fingerprint") != current["fingerprint"]
        ):
            raise ConfigError(
                f"{run_dir} holds a run trained on another data set ({stored.get('path')}, not "
                f"{data_dir}); delete it or choose another results folder"
            )
        if _finished(run_dir, config) and not state.get("batches_done"):  # not mid-epoch
            log(f"{run.name}: already trained ({length})")
            return
        of = config.epochs if config.steps is None else f"a run of {length}"
        log(f"{run.name}: resuming at epoch {done + 1} of {of}")
        summary = train(
            config, data_dir, run_dir, device=device, resume=True, progress=progress, **options
        )
    else:
        log(f"{run.name}: training {length} on {device}")
        summary = train(config, data_dir, run_dir, device=device, progress=progress, **options)
    if summary["interrupted"]:
        raise KeyboardInterrupt


def evaluate_run(run: StudyRun, data_dir: Path, run_dir: Path, device: str) -> dict[str, Any]:
    """Predict the test split with ``best.pt`` and score both regions; the run's record."""
    from pfnet.data import missing_count
    from pfnet.evaluation.reports import write_json
    from pfnet.evaluation.scoring import evaluate_predictions
    from pfnet.inference.checkpoint import load_checkpoint
    from pfnet.inference.predict import predict_split

    checkpoint = run_dir / "best.pt"
    pred_dir = run_dir / "predictions"
    predict_split(checkpoint, data_dir, pred_dir, missing_ratio=run.missing_ratio, device=device)
    reports = {}
    for region in ("missing", "whole"):
        evaluation = evaluate_predictions(
            pred_dir, data_dir, missing_ratio=run.missing_ratio, region=region
        )
        if evaluation.missing or evaluation.unreadable:
            raise DataError(f"{pred_dir}: predictions are missing or unreadable")
        reports[region] = evaluation.report
        write_json(run_dir / f"eval-{region}.json", evaluation.report)
    model, config = load_checkpoint(checkpoint, device="cpu")
    n_points = int(config.n_points)
    history = read_log(run_dir)
    trained = [row for row in history if row["epoch"] > 0]
    curve = [row["val_cd_l2"] for row in trained]
    best = min(range(len(curve)), key=curve.__getitem__)
    return {
        "name": run.name,
        "setting": run.setting,
        "model": run.model,
        "missing_ratio": run.missing_ratio,
        "seed": run.seed,
        **({} if run.steps is None else {"steps": run.steps}),
        "n_missing": missing_count(n_points, run.missing_ratio),
        "parameters": int(sum(p.numel() for p in model.parameters())),
        # Measured wall time, and the median epoch: robust to other load on the machine.
        "train_time_s": round(sum(row.get("time_s", 0.0) for row in trained), 1),
        "epoch_time_s": round(float(np.median([row.get("time_s", 0.0) for row in trained])), 2),
        "epochs": len(trained),
        "best_epoch": trained[best]["epoch"],
        "best_val_cd_l2": curve[best],
        "plateau": plateau(curve),
        "curve": {
            "epoch": [row["epoch"] for row in trained],
            "val_cd_l2": curve,
            "train_cd_detail": [row.get("cd_detail") for row in trained],
        },
        "missing": _summary(reports["missing"]),
        "whole": _summary(reports["whole"]),
    }
