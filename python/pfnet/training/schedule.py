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
    """The run's learning-rate schedule, stepped per epoch (epoch runs) or per optimiser step
    (``config.steps``): ``lr`` times :func:`lr_factor`, in closed form, so that a resumed run
    can be put anywhere on it (:func:`resume_scheduler`)."""

    def factor(index: int) -> float:  # a function, not a callable object: not in state dicts
        return lr_factor(config, index)

    return torch.optim.lr_scheduler.LambdaLR(optimizer, factor)


def lr_factor(config: TrainConfig, index: int) -> float:
    """The factor on ``lr`` after ``index`` scheduler steps (epochs, or optimiser steps in a
    run of ``config.steps``).

    The paper's epoch schedule (``schedule = "fixed"``) multiplies by ``lr_gamma`` every
    ``lr_step`` epochs, as StepLR does. A run sized to its length (``schedule = "run"``, or
    any run of steps) multiplies by ``lr_gamma`` at each of ``lr_milestones`` (fractions of
    the run), or with ``lr_decay = "cosine"`` lowers it along a half cosine to the same
    final rate; a run of steps first warms up linearly over ``warmup_steps`` from
    ``lr / warmup``.
    """
    if config.steps is None and config.schedule == "fixed":
        return config.lr_gamma ** (index // config.lr_step)
    if config.steps is None and config.lr_decay == "step":
        return config.lr_gamma ** sum(index >= m for m in _epoch_milestones(config))
    if config.steps is None:
        return cosine_factor(config, index / config.epochs)
    warmup = config.warmup_steps
    rise = min(1.0, (index + 1) / warmup) if warmup else 1.0
    if config.lr_decay == "cosine":
        return rise * cosine_factor(config, (index - warmup) / max(1, config.steps - warmup))
    milestones = [round(f * config.steps) for f in config.lr_milestones]
    return rise * config.lr_gamma ** sum(index >= m for m in milestones)


def resume_scheduler(scheduler: torch.optim.lr_scheduler.LambdaLR, stored: dict) -> None:
    """Put ``scheduler`` and its optimiser's rate where the stored scheduler state stopped,
    on ``scheduler``'s own schedule.

    Only the stored count is read: a run resumed with more epochs (``--resume --epochs``)
    follows the schedule sized to its new length from where it stopped, not the old
    length's (whose decayed rate the optimiser's stored state still holds), and states of
    the schedulers used before (StepLR, MultiStepLR) resume the same way.
    """
    index = int(stored["last_epoch"])
    scheduler.last_epoch = index
    rates = [base * fn(index) for base, fn in zip(scheduler.base_lrs, scheduler.lr_lambdas)]
    for group, rate in zip(scheduler.optimizer.param_groups, rates):
        group["lr"] = rate
    scheduler._last_lr = rates


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
