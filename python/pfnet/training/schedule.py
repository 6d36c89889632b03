"""Learning-rate and α schedules, in epochs (the paper's) or in fractions of a run of steps.

The paper's schedule (StepLR every 40 epochs, α steps at epochs 30 and 80) assumes
ShapeNet-Part's ~340 steps an epoch. On a data set of a few hundred shapes an epoch is a
dozen steps, and the same schedule leaves the learning rate at 1/5 after 480 steps and at
1.6e-6 by epoch 200: the curves flatten because the learning rate is gone. A run sized in
steps (``TrainConfig.steps``) reads its milestones as fractions of the run instead.
"""

from __future__ import annotations

import math

import torch

from pfnet.training.config import TrainConfig
from pfnet.training.losses import alpha_for_epoch

FEW_STEPS_AT_FULL_LR = 2000  # below this, a run is told that its learning rate decays early


def make_scheduler(
    optimizer: torch.optim.Optimizer, config: TrainConfig
) -> torch.optim.lr_scheduler.LRScheduler:
    """StepLR stepped per epoch (epoch runs), or a per-step schedule (``config.steps``).

    The per-step schedule is a linear warm-up over ``warmup_steps`` from ``lr / warmup``,
    then ``lr`` multiplied by ``lr_gamma`` at each of ``lr_milestones`` (fractions of
    ``steps``), or with ``lr_decay = "cosine"`` lowered along a half cosine to the same
    final rate. An epoch run with ``schedule = "run"`` does the same per epoch, without the
    warm-up.
    """
    if config.steps is None and config.schedule == "fixed":
        return torch.optim.lr_scheduler.StepLR(
            optimizer, step_size=config.lr_step, gamma=config.lr_gamma
        )
    if config.steps is None and config.lr_decay == "step":
        return torch.optim.lr_scheduler.MultiStepLR(
            optimizer, milestones=_epoch_milestones(config), gamma=config.lr_gamma
        )
    if config.steps is None:
        return torch.optim.lr_scheduler.LambdaLR(
            optimizer, lambda epoch: cosine_factor(config, epoch / config.epochs)
        )
    milestones = [round(f * config.steps) for f in config.lr_milestones]
    warmup, gamma = config.warmup_steps, config.lr_gamma

    def factor(step: int) -> float:
        rise = min(1.0, (step + 1) / warmup) if warmup else 1.0
        if config.lr_decay == "cosine":
            return rise * cosine_factor(config, (step - warmup) / max(1, config.steps - warmup))
        return rise * gamma ** sum(step >= m for m in milestones)

    return torch.optim.lr_scheduler.LambdaLR(optimizer, factor)


def cosine_factor(config: TrainConfig, progress: float) -> float:
    """The cosine decay's factor on ``lr`` at ``progress`` (0 to 1) of its span: from 1 to
    the step schedule's final factor, ``lr_gamma ** len(lr_milestones)``."""
    final = config.lr_gamma ** len(config.lr_milestones)
    progress = min(1.0, max(0.0, progress))
    return final + (1.0 - final) * 0.5 * (1.0 + math.cos(math.pi * progress))


def _epoch_milestones(config: TrainConfig) -> list[int]:
    """The epochs at which a ``schedule = "run"`` run drops its learning rate (at least 1)."""
    return [max(1, round(f * config.epochs)) for f in config.lr_milestones]


def run_fraction(config: TrainConfig, epoch: int, step: int) -> float:
    """How much of the run has passed at 0-based ``epoch`` (epoch runs) or global ``step``
    (step runs), as the schedules that are fractions of the run read it."""
    return step / config.steps if config.steps is not None else epoch / config.epochs


def alpha_at(config: TrainConfig, epoch: int, step: int) -> float:
    """α of Eq. (2) at 0-based ``epoch`` (epoch runs) or global ``step`` (step runs)."""
    if config.steps is None and config.schedule == "fixed":
        return alpha_for_epoch(epoch, config.alpha_schedule)
    fraction = run_fraction(config, epoch, step)
    alpha = float(config.alpha_fractions[0][1])
    for first, value in config.alpha_fractions:
        if fraction >= first:
            alpha = float(value)
    return alpha


#: No freeze before this many optimiser steps, whatever fraction the run asks for: at 5 % of a
#: 48-step run (step 3) the running statistics (momentum 0.1) are still mostly their
#: initial values, and the frozen network fits worse than an unfrozen one (tiny-data test).
BATCHNORM_FREEZE_MIN_STEPS = 50


def batchnorm_frozen(config: TrainConfig, epoch: int, step: int) -> bool:
    """Whether the generator's BatchNorm layers use their frozen running statistics at
    0-based ``epoch`` (epoch runs) or global ``step`` (step runs):
    ``config.batchnorm_freeze`` of the run has passed, and at least
    ``BATCHNORM_FREEZE_MIN_STEPS`` optimiser steps."""
    if step < BATCHNORM_FREEZE_MIN_STEPS:
        return False
    return 0 < config.batchnorm_freeze <= run_fraction(config, epoch, step)


def total_epochs(config: TrainConfig, steps_per_epoch: int) -> int:
    """How many epochs the run has (the last one may be partial in a run of steps)."""
    if config.steps is None:
        return config.epochs
    return max(1, math.ceil(config.steps / max(1, steps_per_epoch)))


def steps_at_full_lr(config: TrainConfig, steps_per_epoch: int) -> tuple[int, int]:
    """``(steps at the full learning rate, steps in the run)``."""
    if config.steps is None:
        total = config.epochs * steps_per_epoch
        if config.lr_gamma == 1.0 or (config.schedule == "run" and not config.lr_milestones):
            return total, total
        if config.schedule == "run" and config.lr_decay == "cosine":
            return total // 2, total  # above half the peak rate for the first half
        first = _epoch_milestones(config)[0] if config.schedule == "run" else config.lr_step
        return min(total, first * steps_per_epoch), total
    total = config.steps
    if config.lr_gamma == 1.0 or not config.lr_milestones:
        full = total
    elif config.lr_decay == "cosine":
        full = config.warmup_steps + (total - config.warmup_steps) // 2
    else:
        full = round(config.lr_milestones[0] * total)
    return max(0, full - config.warmup_steps), total


def schedule_note(config: TrainConfig, steps_per_epoch: int) -> str | None:
    """A warning when the run gets few steps at the full learning rate, else ``None``."""
    full, total = steps_at_full_lr(config, steps_per_epoch)
    if full >= FEW_STEPS_AT_FULL_LR or full >= total:
        return None
    if config.lr_decay == "cosine":
        how = "the cosine decay below half the rate after half the run"
    elif config.steps is not None:
        how = f"the first milestone at {config.lr_milestones[0]:g} of {total} steps"
    elif config.schedule == "run":
        how = f"the first milestone at {config.lr_milestones[0]:g} of {config.epochs} epochs"
    else:
        how = f"StepLR every {config.lr_step} epochs of {steps_per_epoch} steps"
    return (
        f"only {full} of the run's {total} optimiser steps are at the full learning rate "
        f"({how}); a flat curve later means the learning rate is gone, not convergence. "
        "Size small data sets in optimiser steps to give them the updates they need"
    )
