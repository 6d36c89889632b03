"""One optimisation step of a generator (and, for PF-Net, its discriminator)."""

from __future__ import annotations

import contextlib
from typing import Any

import torch
from torch import nn
from torch.nn.parallel import DistributedDataParallel

from pfnet.errors import ConfigError
from pfnet.models import Discriminator, build_model, initialise
from pfnet.training.average import WeightAverage
from pfnet.training.config import TrainConfig
from pfnet.training.distributed import DistContext
from pfnet.training.losses import (
    completion_loss,
    discriminator_loss,
    generator_adversarial_loss,
    joint_loss,
)
from pfnet.training.schedule import make_scheduler, resume_scheduler

BATCHNORMS = (nn.BatchNorm1d, nn.BatchNorm2d, nn.BatchNorm3d)


class TrainingStep:
    """The models, optimisers and schedulers of a run, and its per-batch update.

    Adversarial generators (PF-Net) get a :class:`Discriminator`; under DDP both are wrapped
    in ``DistributedDataParallel``. Both networks are initialised by ``config.init``, drawing
    from ``config.seed``.

    Args:
        config: The run's configuration, with ``n_points`` set.
        context: Process / device placement (:func:`pfnet.training.distributed.setup`).
    """

    def __init__(self, config: TrainConfig, context: DistContext) -> None:
        self.config = config
        self.device = device = context.device
        torch.manual_seed(config.seed)
        try:
            generator = build_model(config)
        except ConfigError as err:
            raise ConfigError(
                f"model {config.model!r} with {config.n_points} points and missing_ratio "
                f"{config.missing_ratio}: {err}"
            ) from None
        # Initialised on the CPU, so a seed gives the same start on every device.
        self.generator = initialise(generator, config.init).to(device)
        self.multi_stage = generator.multi_stage
        self.discriminator = (
            initialise(Discriminator(config.width), config.init).to(device)
            if generator.adversarial
            else None
        )
        self.g_forward: nn.Module = self.generator
        self.d_forward: nn.Module | None = self.discriminator
        if context.distributed:
            ids = [device] if device.type == "cuda" else None
            self.g_forward = DistributedDataParallel(self.generator, device_ids=ids)
            if self.discriminator is not None:
                self.d_forward = DistributedDataParallel(self.discriminator, device_ids=ids)
        if config.compile:
            # The compiled wrappers only run the forward passes; the state dicts stay those
            # of the plain modules (no "_orig_mod." prefixes in checkpoints).
            self.g_forward = torch.compile(self.g_forward)
            if self.d_forward is not None:
                self.d_forward = torch.compile(self.d_forward)
        self.optimizer_g = self._adam(self.generator)
        self.scheduler_g = make_scheduler(self.optimizer_g, config)
        self.optimizer_d = self._adam(self.discriminator) if self.discriminator else None
        self.scheduler_d = make_scheduler(self.optimizer_d, config) if self.optimizer_d else None
        self.average = WeightAverage(self.generator, config.ema) if config.ema > 0 else None
        self.batchnorms = [m for m in self.generator.modules() if isinstance(m, BATCHNORMS)]
        #: Set by the loop from ``config.batchnorm_freeze``: the generator's BatchNorm
        #: layers then normalise by their running statistics and stop updating them.
        self.batchnorm_frozen = False

    @property
    def scored(self) -> nn.Module:
        """The generator that validation scores and ``best.pt`` holds: the average, if any."""
        return self.average.model if self.average is not None else self.generator

    def restart_average(self) -> None:
        """Start the weight average again from the generator (after loading weights)."""
        if self.average is not None:
            self.average.reset(self.generator)

    def _adam(self, module: nn.Module) -> torch.optim.Adam:
        c = self.config
        return torch.optim.Adam(
            module.parameters(), lr=c.lr, betas=c.betas, eps=c.eps, weight_decay=c.weight_decay
        )

    @property
    def lr(self) -> float:
        """The generator's current learning rate."""
        return float(self.optimizer_g.param_groups[0]["lr"])

    def autocast(self) -> contextlib.AbstractContextManager:
        """The precision context of the networks' forward passes (``config.precision``).

        bf16 runs them under ``torch.autocast``; the Chamfer terms switch autocast off and
        compute in float32 (:func:`pfnet.training.losses.chamfer_distance`), and the BCE losses
        are on autocast's float32 list.
        """
        if self.config.precision == "bf16":
            return torch.autocast(self.device.type, dtype=torch.bfloat16)
        return contextlib.nullcontext()

    def end_epoch(self) -> None:
        """Advance the learning-rate schedules by one epoch (runs sized in epochs)."""
        if self.config.steps is None:
            self._advance()

    def end_step(self) -> None:
        """Advance the learning-rate schedules by one step (runs sized in steps)."""
        if self.config.steps is not None:
            self._advance()

    def _advance(self) -> None:
        self.scheduler_g.step()
        if self.scheduler_d is not None:
            self.scheduler_d.step()

    def state_dict(self) -> dict[str, Any]:
        """Models, optimisers, schedulers and the weight average (``None`` where absent)."""
        d, od, sd = self.discriminator, self.optimizer_d, self.scheduler_d
        return {
            "average": self.average.state_dict() if self.average is not None else None,
            "model": self.generator.state_dict(),
            "discriminator": d.state_dict() if d is not None else None,
            "optimizer_g": self.optimizer_g.state_dict(),
            "optimizer_d": od.state_dict() if od is not None else None,
            "scheduler_g": self.scheduler_g.state_dict(),
            "scheduler_d": sd.state_dict() if sd is not None else None,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`state_dict` returned."""
        self.generator.load_state_dict(state["model"])
        self.optimizer_g.load_state_dict(state["optimizer_g"])
        resume_scheduler(self.scheduler_g, state["scheduler_g"])
        if self.average is not None:
            self.average.load_state_dict(state["average"])
        if self.discriminator is not None:
            self.discriminator.load_state_dict(state["discriminator"])
            self.optimizer_d.load_state_dict(state["optimizer_d"])
            resume_scheduler(self.scheduler_d, state["scheduler_d"])

    def __call__(self, batch: dict[str, Any], alpha: float) -> dict[str, float]:
        """One discriminator step (adversarial models) then one generator step.

        Args:
            batch: A batch from :class:`CompletionCollate`.
            alpha: α of the multi-stage completion loss for this epoch.

        Returns:
            The batch's losses as floats (``loss_g``, ``cd_detail``, ... and, with a
            discriminator, ``loss_d`` and ``adv_g``).
        """
        device = self.device
        partial = batch["partial"].to(device, non_blocking=True)
        missing = batch["missing"].to(device, non_blocking=True)
        scale_indices = batch.get("scale_indices")
        secondary_target = batch.get("secondary_target")
        primary_target = batch.get("primary_target")
        if secondary_target is not None and primary_target is not None:
            secondary_target = secondary_target.to(device, non_blocking=True)
            primary_target = primary_target.to(device, non_blocking=True)

        if self.batchnorm_frozen:  # again every step: validation puts them back in training
            for layer in self.batchnorms:
                layer.eval()
        with self.autocast():
            completion = self.g_forward(partial, scale_indices)
        losses: dict[str, float] = {}
        if self.d_forward is not None and self.optimizer_d is not None:
            # Real and fake are back-propagated one after the other, as the authors do, so
            # BatchNorm sees each set on its own.
            self.optimizer_d.zero_grad(set_to_none=True)
            with self.autocast():
                loss_real = discriminator_loss(self.d_forward(missing), real=True)
            loss_real.backward()
            with self.autocast():
                fake_logits = self.d_forward(completion.detail.detach())
                loss_fake = discriminator_loss(fake_logits, real=False)
            loss_fake.backward()
            self.optimizer_d.step()
            losses["loss_d"] = float(loss_real.detach() + loss_fake.detach())

        self.optimizer_g.zero_grad(set_to_none=True)
        loss_com, parts = completion_loss(
            completion,
            missing,
            secondary_target,
            primary_target,
            alpha=alpha,
            scale=self.config.loss_scale,
            chamfer=self.config.chamfer,
        )
        if self.d_forward is not None:
            with self.autocast():
                adversarial = generator_adversarial_loss(self.d_forward(completion.detail))
            loss_g = joint_loss(loss_com, adversarial.float(), self.config.adversarial_weight)
            losses["adv_g"] = float(adversarial.detach())
        else:
            loss_g = loss_com
        loss_g.backward()
        if self.config.grad_clip > 0:  # not in the paper: a lever for small, spiky batches
            norm = torch.nn.utils.clip_grad_norm_(
                self.generator.parameters(), self.config.grad_clip
            )
            losses["grad_norm"] = float(norm)
        self.optimizer_g.step()
        if self.average is not None:
            self.average.update(self.generator)
        losses["loss_g"] = float(loss_g.detach())
        losses.update({k: float(v) for k, v in parts.items()})
        return losses
