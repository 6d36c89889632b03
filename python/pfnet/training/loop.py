"""One training loop for every model: PF-Net (with its discriminator) and the baselines.

Per batch, adversarial models take one discriminator step then one generator step (as the
authors' ``Train_PFNet.py``); the others take a generator step on the completion loss alone.
After every epoch the generator is validated on the ``val`` split with the deterministic test
protocol and the same metric functions as ``pfnet evaluate`` (:mod:`pfnet.metrics`), and
``RUN/last.pt``, ``RUN/best.pt``, ``RUN/log.jsonl`` and ``RUN/curves.png`` are rewritten
atomically (by rank 0 only under DDP).
"""

from __future__ import annotations

import contextlib
import json
import math
import multiprocessing
import multiprocessing.context
import signal
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import BatchSampler, DataLoader, DistributedSampler, Sampler, Subset
from tqdm import tqdm

from pfnet.checkpoint import read_checkpoint, save_checkpoint
from pfnet.errors import ConfigError, DataError
from pfnet.geometry import farthest_point_sample
from pfnet.io import atomic_path
from pfnet.losses import (
    alpha_for_epoch,
    completion_loss,
    discriminator_loss,
    generator_adversarial_loss,
    joint_loss,
)
from pfnet.models import Discriminator, build_model
from pfnet.models.layers import multi_resolution_indices
from pfnet.models.pfnet import PRIMARY_POINTS, SECONDARY_POINTS
from pfnet.training import distributed
from pfnet.training.config import RESUMABLE_FIELDS, TrainConfig
from pfnet.training.distributed import DistContext

LAST = "last.pt"
BEST = "best.pt"
LOG = "log.jsonl"
CURVES = "curves.png"
VAL_METRIC = "val_cd_l2"  # selects best.pt: Pred→GT + GT→Pred on the missing region, ×1000


def train(
    config: TrainConfig,
    data_dir: str | Path,
    out_dir: str | Path,
    *,
    device: str | torch.device = "auto",
    resume: bool = False,
    progress: bool | None = None,
) -> dict[str, Any]:
    """Train ``config.model`` on the dataset in ``data_dir``, writing the run to ``out_dir``.

    Under ``torchrun`` every process calls this; they train with DistributedDataParallel and
    only rank 0 writes files.

    Args:
        config: The run's configuration (``n_points`` may be unset: taken from the data).
        data_dir: A dataset prepared by ``pfnet prepare`` (``train`` and ``val`` splits).
        out_dir: The run folder (created; must not hold a run unless ``resume``).
        device: ``auto``, ``cpu``, ``cuda`` or ``cuda:N``.
        resume: Continue the run in ``out_dir`` from its ``last.pt`` exactly where it
            stopped (mid-epoch after Ctrl-C). Only ``epochs`` and ``workers`` may differ
            from the stored configuration.
        progress: Show a tqdm bar (default: when stderr is a terminal).

    Returns:
        A summary: ``epochs`` completed, ``interrupted``, ``best_epoch``, ``best_val_cd_l2``,
        ``last`` / ``best`` checkpoint paths, ``world_size`` and the final log row ``final``.

    Raises:
        ConfigError: Bad configuration, or a resume that changes the configuration.
        DataError: Missing or unusable dataset or checkpoint.
    """
    context = distributed.setup(device)
    try:
        trainer = Trainer(config, Path(data_dir), Path(out_dir), context, resume=resume)
        show = sys.stderr.isatty() if progress is None else progress
        return trainer.run(progress=show and context.is_main)
    finally:
        distributed.teardown(context)


class CompletionCollate:
    """Stacks dataset items and adds the IFPS index sets the losses and encoders need.

    Runs in data-loader workers, so the Rust sampling overlaps the training step.

    Args:
        multi_resolution: Add ``scale_indices`` (``(B, n // 2)`` IFPS of the partial cloud).
        centre_targets: Add ``secondary_target`` (``(B, 128, 3)`` IFPS of the missing points)
            and ``primary_target`` (its first 64 points, which are the 64-point IFPS).
    """

    def __init__(self, multi_resolution: bool, centre_targets: bool) -> None:
        self.multi_resolution = multi_resolution
        self.centre_targets = centre_targets

    def __call__(self, items: list[dict[str, Any]]) -> dict[str, Any]:
        """Collate a list of ``CompletionDataset`` items into a batch dict."""
        batch: dict[str, Any] = {
            key: torch.stack([item[key] for item in items])
            for key in ("partial", "missing", "complete")
        }
        batch["category"] = [item["category"] for item in items]
        batch["index"] = torch.tensor([int(item["index"]) for item in items])
        if self.multi_resolution:
            batch["scale_indices"] = torch.from_numpy(
                multi_resolution_indices(batch["partial"].numpy())
            )
        if self.centre_targets:
            missing = batch["missing"]
            index = torch.from_numpy(
                np.asarray(farthest_point_sample(missing.numpy(), SECONDARY_POINTS), np.int64)
            )
            secondary = torch.gather(missing, 1, index.unsqueeze(-1).expand(-1, -1, 3))
            batch["secondary_target"] = secondary
            batch["primary_target"] = secondary[:, :PRIMARY_POINTS].contiguous()
        return batch


class SkipBatches(Sampler[list[int]]):
    """A batch sampler that leaves out the first ``skip`` batches (mid-epoch resume)."""

    def __init__(self, batches: BatchSampler, skip: int = 0) -> None:
        self.batches = batches
        self.skip = skip

    def __iter__(self) -> Iterator[list[int]]:
        for i, batch in enumerate(self.batches):
            if i >= self.skip:
                yield batch

    def __len__(self) -> int:
        return max(0, len(self.batches) - self.skip)


def _worker_context() -> multiprocessing.context.BaseContext:
    """Start data-loader workers from a fork server that has imported pfnet but run nothing.

    A plain ``fork`` after the Rust core has run in this process copies its thread pool's
    state without its threads, and the first batched call in the child never returns.
    """
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(["pfnet.training.loop"])
    return context


def _ignore_sigint(_worker_id: int) -> None:
    # Ctrl-C reaches the whole process group; the main process decides when to stop, and
    # workers killed mid-batch would make its last fetch fail.
    signal.signal(signal.SIGINT, signal.SIG_IGN)


class _StopRequest:
    """SIGINT/SIGTERM handler: the first signal asks to stop after the current batch."""

    def __init__(self) -> None:
        self.requested = False
        self._previous: dict[int, Any] = {}

    def _handle(self, signum: int, _frame: object) -> None:
        if self.requested and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.requested = True
        print(
            "\npfnet train: stopping after this batch and saving (Ctrl-C again to abort)",
            file=sys.stderr,
        )

    @contextlib.contextmanager
    def installed(self) -> Iterator[_StopRequest]:
        import threading

        if threading.current_thread() is not threading.main_thread():
            yield self
            return
        for signum in (signal.SIGINT, signal.SIGTERM):
            self._previous[signum] = signal.signal(signum, self._handle)
        try:
            yield self
        finally:
            for signum, handler in self._previous.items():
                signal.signal(signum, handler)


class TrainingStep:
    """The models, optimisers and schedulers of a run, and its per-batch update.

    Adversarial generators (PF-Net) get a :class:`Discriminator`; under DDP both are wrapped
    in ``DistributedDataParallel``. Models are initialised from ``config.seed``.

    Args:
        config: The run's configuration, with ``n_points`` set.
        context: Process / device placement (:func:`pfnet.training.distributed.setup`).
    """

    def __init__(self, config: TrainConfig, context: DistContext) -> None:
        self.config = config
        self.device = device = context.device
        torch.manual_seed(config.seed)
        try:
            self.generator = build_model(config).to(device)
        except ConfigError as err:
            raise ConfigError(
                f"model {config.model!r} with {config.n_points} points and missing_ratio "
                f"{config.missing_ratio}: {err}"
            ) from None
        self.multi_stage = bool(getattr(self.generator, "multi_stage", False))
        adversarial = bool(getattr(self.generator, "adversarial", False))
        self.discriminator = Discriminator(config.width).to(device) if adversarial else None
        self.g_forward: nn.Module = self.generator
        self.d_forward: nn.Module | None = self.discriminator
        if context.distributed:
            ids = [device] if device.type == "cuda" else None
            self.g_forward = DistributedDataParallel(self.generator, device_ids=ids)
            if self.discriminator is not None:
                self.d_forward = DistributedDataParallel(self.discriminator, device_ids=ids)
        self.optimizer_g = self._adam(self.generator)
        self.scheduler_g = self._step_lr(self.optimizer_g)
        self.optimizer_d = self._adam(self.discriminator) if self.discriminator else None
        self.scheduler_d = self._step_lr(self.optimizer_d) if self.optimizer_d else None

    def _adam(self, module: nn.Module) -> torch.optim.Adam:
        c = self.config
        return torch.optim.Adam(
            module.parameters(), lr=c.lr, betas=c.betas, eps=c.eps, weight_decay=c.weight_decay
        )

    def _step_lr(self, optimizer: torch.optim.Optimizer) -> torch.optim.lr_scheduler.StepLR:
        return torch.optim.lr_scheduler.StepLR(
            optimizer, step_size=self.config.lr_step, gamma=self.config.lr_gamma
        )

    @property
    def lr(self) -> float:
        """The generator's current learning rate."""
        return float(self.optimizer_g.param_groups[0]["lr"])

    def end_epoch(self) -> None:
        """Advance the learning-rate schedules by one epoch."""
        self.scheduler_g.step()
        if self.scheduler_d is not None:
            self.scheduler_d.step()

    def state_dict(self) -> dict[str, Any]:
        """Models, optimisers and schedulers (``None`` where there is no discriminator)."""
        d, od, sd = self.discriminator, self.optimizer_d, self.scheduler_d
        return {
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
        self.scheduler_g.load_state_dict(state["scheduler_g"])
        if self.discriminator is not None:
            self.discriminator.load_state_dict(state["discriminator"])
            self.optimizer_d.load_state_dict(state["optimizer_d"])
            self.scheduler_d.load_state_dict(state["scheduler_d"])

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

        completion = self.g_forward(partial, scale_indices)
        losses: dict[str, float] = {}
        if self.d_forward is not None and self.optimizer_d is not None:
            # Real and fake are back-propagated one after the other, as the authors do, so
            # BatchNorm sees each set on its own.
            self.optimizer_d.zero_grad(set_to_none=True)
            loss_real = discriminator_loss(self.d_forward(missing), real=True)
            loss_real.backward()
            loss_fake = discriminator_loss(self.d_forward(completion.detail.detach()), real=False)
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
        )
        if self.d_forward is not None:
            adversarial = generator_adversarial_loss(self.d_forward(completion.detail))
            loss_g = joint_loss(loss_com, adversarial, self.config.adversarial_weight)
            losses["adv_g"] = float(adversarial.detach())
        else:
            loss_g = loss_com
        loss_g.backward()
        self.optimizer_g.step()
        losses["loss_g"] = float(loss_g.detach())
        losses.update({k: float(v) for k, v in parts.items()})
        return losses


class Trainer:
    """State of one training run; see :func:`train`."""

    def __init__(
        self,
        config: TrainConfig,
        data_dir: Path,
        out_dir: Path,
        context: DistContext,
        *,
        resume: bool = False,
    ) -> None:
        from pfnet.data.dataset import CompletionDataset

        self.context = context
        self.device = context.device
        self.out_dir = out_dir
        if out_dir.exists() and not out_dir.is_dir():
            raise ConfigError(f"--out {out_dir} exists and is not a folder")
        state = None
        if resume:
            state = read_checkpoint(out_dir / LAST, "cpu")
            config = _resumed_config(config, state, out_dir / LAST)
            if state["batches_done"] and state["world_size"] != context.world_size:
                raise ConfigError(
                    f"{out_dir / LAST} was saved mid-epoch by {state['world_size']} process(es); "
                    f"resume it with the same number, not {context.world_size}"
                )
        elif (out_dir / LAST).exists():
            raise ConfigError(
                f"{out_dir} already holds a run ({LAST}); pass --resume to continue it "
                "or choose another --out"
            )

        self.train_set = CompletionDataset(
            data_dir,
            "train",
            missing_ratio=config.missing_ratio,
            crop=config.crop,
            seed=config.seed,
        )
        self.val_set = CompletionDataset(
            data_dir, "val", missing_ratio=config.missing_ratio, crop="test", seed=config.seed
        )
        if len(self.train_set) == 0:
            raise DataError(f"{data_dir}: the train split is empty")
        n_points = int(self.train_set.n_points)
        if config.n_points is not None and config.n_points != n_points:
            raise ConfigError(
                f"n_points is {config.n_points} but the clouds in {data_dir} have {n_points} points"
            )
        self.config = config = config.replace(n_points=n_points)

        self.step = TrainingStep(config, context)
        self.generator = self.step.generator
        self.sampler = DistributedSampler(
            self.train_set,
            num_replicas=context.world_size,
            rank=context.rank,
            shuffle=True,
            seed=config.seed,
        )
        self.collate = CompletionCollate(
            multi_resolution=bool(getattr(self.generator, "multi_resolution", False)),
            centre_targets=self.step.multi_stage,
        )
        self.epoch = 0
        self.batches_done = 0
        self.epoch_sums: dict[str, float] = {}
        self.best_metric = math.inf
        self.best_epoch: int | None = None
        self.history: list[dict[str, Any]] = []
        if state is not None:
            self._load_state(state)

    # -- data --------------------------------------------------------------------------

    def _train_loader(self, skip: int) -> DataLoader:
        batches = BatchSampler(self.sampler, self.config.batch_size, drop_last=False)
        workers = self.config.workers
        return DataLoader(
            self.train_set,
            batch_sampler=SkipBatches(batches, skip),
            num_workers=workers,
            collate_fn=self.collate,
            worker_init_fn=_ignore_sigint if workers else None,
            multiprocessing_context=_worker_context() if workers else None,
            pin_memory=self.device.type == "cuda",
        )

    # -- checkpoints ---------------------------------------------------------------------

    def _state(self) -> dict[str, Any]:
        rng: dict[str, Any] = {"torch": torch.get_rng_state()}
        if torch.cuda.is_available():
            rng["cuda"] = torch.cuda.get_rng_state_all()
        return {
            "config": self.config.to_dict(),
            **self.step.state_dict(),
            "epoch": self.epoch,
            "batches_done": self.batches_done,
            "epoch_sums": dict(self.epoch_sums),
            "best_metric": self.best_metric,
            "best_epoch": self.best_epoch,
            "history": self.history,
            "rng": rng,
            "world_size": self.context.world_size,
        }

    def _load_state(self, state: dict[str, Any]) -> None:
        self.step.load_state_dict(state)
        self.epoch = int(state["epoch"])
        self.batches_done = int(state["batches_done"])
        self.epoch_sums = dict(state["epoch_sums"])
        self.best_metric = float(state["best_metric"])
        self.best_epoch = state["best_epoch"]
        self.history = list(state["history"])
        torch.set_rng_state(state["rng"]["torch"])
        if "cuda" in state["rng"] and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(state["rng"]["cuda"])

    def _save(self, name: str) -> Path:
        path = self.out_dir / name
        if self.context.is_main:
            save_checkpoint(path, self._state())
        return path

    # -- validation ----------------------------------------------------------------------

    @torch.no_grad()
    def validate(self) -> dict[str, float]:
        """Metrics of the generator on the val split (test protocol), ``val_*`` keys, ×1000.

        Empty when the val split is empty.
        """
        from pfnet.metrics import sample_metrics, summarize

        ctx = self.context
        shard = Subset(self.val_set, range(ctx.rank, len(self.val_set), ctx.world_size))
        loader = DataLoader(
            shard,
            batch_size=self.config.batch_size,
            num_workers=0,
            collate_fn=CompletionCollate(self.collate.multi_resolution, centre_targets=False),
        )
        self.generator.eval()
        rows: list[tuple[int, str, dict[str, float]]] = []
        for batch in loader:
            partial = batch["partial"].to(self.device)
            detail = self.generator(partial, batch.get("scale_indices")).detail
            metrics = sample_metrics(detail.float().cpu().numpy(), batch["missing"].numpy())
            for j, index in enumerate(batch["index"].tolist()):
                values = {k: float(v[j]) for k, v in metrics.items()}
                rows.append((index, batch["category"][j], values))
        self.generator.train()
        gathered = distributed.all_gather_objects(rows, ctx)
        rows = sorted((r for part in gathered for r in part), key=lambda r: r[0])
        if not rows:
            return {}
        per_sample = {k: np.array([r[2][k] for r in rows]) for k in rows[0][2]}
        summary = summarize(per_sample, [r[1] for r in rows])["mean"]
        return {f"val_{k}": float(v) for k, v in summary.items() if k != "n"}

    # -- the loop ------------------------------------------------------------------------

    def run(self, progress: bool = False) -> dict[str, Any]:
        """Train until ``config.epochs`` or a stop request; see :func:`train`."""
        ctx = self.context
        c = self.config
        if ctx.is_main:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            with atomic_path(self.out_dir / "config.json") as tmp:
                tmp.write_text(json.dumps(c.to_dict(), indent=2) + "\n")
        if not self.history:
            # Epoch 0: the untrained model, the reference the curves start from.
            self.history.append({"epoch": 0, **self.validate()})
        interrupted = False
        with _StopRequest().installed() as stop:
            while self.epoch < c.epochs and not interrupted:
                interrupted = self._run_epoch(stop, progress)
        if ctx.is_main:
            _write_log(self.out_dir / LOG, self.history)
            _plot_curves(self.out_dir / CURVES, self.history)
        return {
            "epochs": self.epoch,
            "interrupted": interrupted,
            "batches_done": self.batches_done,
            "best_epoch": self.best_epoch,
            "best_val_cd_l2": None
            if math.isinf(self.best_metric) or not len(self.val_set)
            else self.best_metric,
            "last": str(self.out_dir / LAST),
            "best": str(self.out_dir / BEST),
            "world_size": ctx.world_size,
            "final": self.history[-1],
        }

    def _run_epoch(self, stop: _StopRequest, progress: bool) -> bool:
        """Train one epoch (or its rest); returns True if it stopped on request."""
        c, ctx = self.config, self.context
        epoch = self.epoch
        alpha = alpha_for_epoch(epoch, c.alpha_schedule)
        self.train_set.set_epoch(epoch)
        self.sampler.set_epoch(epoch)
        loader = self._train_loader(self.batches_done)
        started = time.perf_counter()
        total = len(loader) + self.batches_done
        bar = tqdm(
            total=total,
            initial=self.batches_done,
            desc=f"epoch {epoch + 1}/{c.epochs}",
            disable=not progress,
            leave=False,
            dynamic_ncols=True,
        )
        with bar:
            for batch in loader:
                losses = self.step(batch, alpha)
                size = len(batch["index"])
                for key, value in losses.items():
                    self.epoch_sums[key] = self.epoch_sums.get(key, 0.0) + value * size
                self.epoch_sums["count"] = self.epoch_sums.get("count", 0.0) + size
                self.batches_done += 1
                count = self.epoch_sums["count"]
                bar.set_postfix(
                    {k: f"{v / count:.4g}" for k, v in self.epoch_sums.items() if k != "count"},
                    refresh=False,
                )
                bar.update()
                if distributed.any_rank(stop.requested, ctx):
                    path = self._save(LAST)
                    if ctx.is_main:
                        print(
                            f"pfnet train: saved {path} at epoch {epoch + 1}, batch "
                            f"{self.batches_done}; continue with --resume",
                            file=sys.stderr,
                        )
                    return True

        row = {"epoch": epoch + 1, "lr": self.step.lr, "alpha": alpha}
        row.update(self._epoch_means())
        self.step.end_epoch()
        row.update(self.validate())
        row["time_s"] = round(time.perf_counter() - started, 3)
        self.history.append(row)
        self.epoch += 1
        self.batches_done = 0
        self.epoch_sums = {}
        # Without validation shapes, best.pt follows the training Chamfer loss.
        metric = row.get(VAL_METRIC, row["cd_detail"])
        improved = metric < self.best_metric
        if improved:
            self.best_metric = metric
            self.best_epoch = epoch + 1
        self._save(LAST)
        if improved:
            self._save(BEST)
        if ctx.is_main:
            _write_log(self.out_dir / LOG, self.history)
            _plot_curves(self.out_dir / CURVES, self.history)
            shown = ", ".join(
                f"{k} {row[k]:.4g}"
                for k in ("loss_g", "loss_d", "cd_detail", VAL_METRIC)
                if k in row
            )
            print(
                f"epoch {epoch + 1}/{c.epochs}: {shown}{' (best)' if improved else ''}",
                file=sys.stderr,
            )
        # A stop requested during validation: the epoch is complete and saved.
        return distributed.any_rank(stop.requested, ctx) and self.epoch < c.epochs

    def _epoch_means(self) -> dict[str, float]:
        """Mean training losses of the epoch over all processes."""
        keys = sorted(k for k in self.epoch_sums if k != "count")
        values = torch.tensor(
            [self.epoch_sums[k] for k in keys] + [self.epoch_sums.get("count", 0.0)],
            dtype=torch.float64,
        )
        if self.context.distributed:
            import torch.distributed as dist

            values = values.to(self.device)
            dist.all_reduce(values)
            values = values.cpu()
        count = float(values[-1]) or 1.0
        return {k: float(v) / count for k, v in zip(keys, values[:-1].tolist(), strict=True)}


def _resumed_config(config: TrainConfig, state: dict[str, Any], path: Path) -> TrainConfig:
    """The stored config with the resumable fields of ``config``; refuse other changes."""
    stored = TrainConfig.from_dict(state["config"], source=f"checkpoint {path}")
    requested = config.to_dict()
    for key, value in stored.to_dict().items():
        if key in RESUMABLE_FIELDS or (key == "n_points" and requested[key] is None):
            continue
        if requested[key] != value:
            raise ConfigError(
                f"cannot change {key} when resuming: {path} was trained with {value!r}, "
                f"got {requested[key]!r}"
            )
    return stored.replace(**{k: requested[k] for k in RESUMABLE_FIELDS})


def _write_log(path: Path, history: list[dict[str, Any]]) -> None:
    """Rewrite the per-epoch JSON-lines log."""
    with atomic_path(path) as tmp:
        tmp.write_text("".join(json.dumps(row) + "\n" for row in history))


def _plot_curves(path: Path, history: list[dict[str, Any]]) -> None:
    """Plot training losses and validation Chamfer distances against the epoch."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt
    from matplotlib.ticker import MaxNLocator

    fig, (ax_loss, ax_val) = plt.subplots(1, 2, figsize=(10, 4))
    for key in ("loss_g", "cd_detail", "cd_secondary", "cd_primary", "loss_d", "adv_g"):
        points = [(r["epoch"], r[key]) for r in history if key in r]
        if points:
            ax_loss.plot(*zip(*points, strict=True), marker=".", label=key)
    ax_loss.set(xlabel="epoch", ylabel="training loss", title="Training losses")
    for key, label in (
        ("val_cd_l2", "CD-L2 (Pred→GT + GT→Pred)"),
        ("val_pred_to_gt", "Pred→GT"),
        ("val_gt_to_pred", "GT→Pred"),
    ):
        points = [(r["epoch"], r[key]) for r in history if key in r]
        if points:
            ax_val.plot(*zip(*points, strict=True), marker=".", label=label)
    ax_val.set(xlabel="epoch", ylabel="×1000, missing region", title="Validation (test protocol)")
    for ax in (ax_loss, ax_val):
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        if ax.lines:
            ax.set_yscale("log")
            ax.legend(fontsize="small")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
