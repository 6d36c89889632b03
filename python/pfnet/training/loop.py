"""One training loop for every model: PF-Net (with its discriminator) and the baselines.

Per batch, adversarial models take one discriminator step then one generator step (as the
authors' ``Train_PFNet.py``); the others take a generator step on the completion loss alone.
After every epoch the generator (its weight average, with ``ema``) is validated on the
``val`` split with the deterministic test protocol (the scanner's for a run trained on
scanner partials, :func:`pfnet.data.dataset.validation_crop`) and the same metric functions as
``pfnet evaluate`` (:mod:`pfnet.evaluation.metrics`).

Files of a run folder (written by rank 0 only under DDP, each replaced atomically):
``log.jsonl`` after every epoch; ``best.pt`` (what inference needs) whenever validation
improves; ``last.pt`` (the full state, for ``--resume``) every ``save_every``, at the end and
on a stop; ``curves.png`` at most every :data:`CURVES_EVERY_S` seconds and at the end.
Checkpoints are serialised on a background thread (:mod:`pfnet.training.saving`), data-loader
workers live for the whole run, and the validation batches are built once, so an epoch's wall
time is spent in training and validation steps.
"""

from __future__ import annotations

import json
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch.utils.data import DataLoader, DistributedSampler
from tqdm import tqdm

from pfnet.data.augment import augmentation_for, scan_up_axis
from pfnet.errors import ConfigError, DataError
from pfnet.inference.checkpoint import read_checkpoint
from pfnet.io.files import atomic_path, refuse_overlap
from pfnet.io.locks import writing
from pfnet.processes import ignore_stop_signals, start_helpers
from pfnet.training import distributed
from pfnet.training.batches import CompletionCollate, EpochBatches
from pfnet.training.config import SaveSchedule, TrainConfig
from pfnet.training.distributed import DistContext
from pfnet.training.resume import check_resumable, data_identity, resumed_config, start_from
from pfnet.training.runlog import epoch_line, plot_curves, write_log
from pfnet.training.saving import CheckpointWriter, cpu_snapshot
from pfnet.training.schedule import alpha_at, batchnorm_frozen, schedule_note, total_epochs
from pfnet.training.signals import StopRequest
from pfnet.training.step import TrainingStep
from pfnet.training.validation import score_generator, validation_batches

LAST = "last.pt"
BEST = "best.pt"
LOG = "log.jsonl"
CURVES = "curves.png"
VAL_METRIC = "val_cd_l2"  # selects best.pt: Pred→GT + GT→Pred on the missing region, ×1000
CURVES_EVERY_S = 60.0  # curves.png is redrawn at most this often (and at the end)
Notes = Callable[[str], None] | None  # what the caller hears, see train()
OnStop = Callable[[], None] | None


def train(
    config: TrainConfig,
    data_dir: str | Path,
    out_dir: str | Path,
    *,
    device: str | torch.device = "auto",
    resume: bool = False,
    progress: bool | None = None,
    val_data: str | Path | None = None,
    notes: Notes = None,
    say: Notes = None,
    on_stop: OnStop = None,
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
            stopped (mid-epoch after Ctrl-C). Only the fields in
            :data:`~pfnet.training.config.RESUMABLE_FIELDS` may differ from the stored
            configuration.
        progress: Show a tqdm bar (default: when stderr is a terminal).
        val_data: Take the ``val`` split from this data set instead (e.g. train on every
            catalogue model, validate on the 8 categories' split, which the wider set's
            train split leaves out).
        notes: Called with each note on the run (a short schedule); ``pfnet train`` prints.
        say: Called with each line of the run's progress (every epoch's losses, the CPU taken
            for too few GPUs), and ``on_stop`` when a signal asks the run to stop at the next
            safe point; ``pfnet train`` prints both.

    Returns:
        A summary: ``epochs`` completed, ``interrupted``, ``best_epoch``, ``best_val_cd_l2``,
        ``last`` / ``best`` checkpoint paths, ``world_size``, the final log row ``final``
        and ``checkpoint_write_s`` (seconds the writer thread spent serialising).

    Raises:
        ConfigError: Bad configuration, or a resume that changes the configuration.
        DataError: Missing or unusable dataset or checkpoint.
    """
    init = [config.init_from] if config.init_from and Path(config.init_from).exists() else []
    inputs = [data_dir, *([val_data] if val_data else []), *init]
    refuse_overlap(out_dir, inputs, flag="run folder")
    context = distributed.setup(device, say)
    finished = False
    try:  # one run in a run folder at a time (a second, or a --resume of one going, is refused)
        with writing(out_dir, "training into", hold=context.is_main):
            val_dir = None if val_data is None else Path(val_data)
            trainer = Trainer(
                config, Path(data_dir), Path(out_dir), context, resume=resume, val_dir=val_dir
            )
            show = sys.stderr.isatty() if progress is None else progress
            summary = trainer.run(
                progress=show and context.is_main, notes=notes, say=say, on_stop=on_stop
            )
            finished = True
            return summary
    finally:
        distributed.teardown(context, finished=finished)


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
        val_dir: Path | None = None,
    ) -> None:
        from pfnet.data.dataset import CompletionDataset, validation_crop

        self.context = context
        self.device = context.device
        self.out_dir = out_dir
        if out_dir.exists() and not out_dir.is_dir():
            raise ConfigError(f"run folder {out_dir} exists and is not a folder")
        state = None
        self.data_identity = data_identity(data_dir)
        if resume:
            state = read_checkpoint(out_dir / LAST, "cpu")
            check_resumable(state, out_dir / LAST)
            config = resumed_config(config, state, out_dir / LAST)
            stored = state.get("data")  # absent in checkpoints of older pfnet versions
            comparable = stored and stored.get("kind") == self.data_identity["kind"]
            if comparable and stored.get("fingerprint") != self.data_identity["fingerprint"]:
                raise ConfigError(
                    f"{out_dir / LAST} trained on another data set ({stored.get('path')}); "
                    f"the data set {data_dir} differs from it: resume with the same data"
                )
            if state["batches_done"] and state["world_size"] != context.world_size:
                raise ConfigError(
                    f"{out_dir / LAST} was saved mid-epoch by {state['world_size']} process(es); "
                    f"resume it with the same number, not {context.world_size}"
                )
        elif (out_dir / LAST).exists():
            raise ConfigError(
                f"{out_dir} already holds a run ({LAST}); resume it to continue, "
                "or choose another run folder"
            )

        self.train_set = CompletionDataset(
            data_dir,
            "train",
            missing_ratio=config.missing_ratio,
            crop=config.crop,
            seed=config.seed,
            fresh_points=config.fresh_points,
            augment=augmentation_for(config, data_dir),
            frame=config.frame,
            up_axis=scan_up_axis(config, data_dir),
        )
        self.val_set = CompletionDataset(
            val_dir or data_dir,
            "val",
            missing_ratio=config.missing_ratio,
            crop=validation_crop(config.crop),
            seed=config.seed,
            frame=config.frame,
            up_axis=scan_up_axis(config, val_dir or data_dir),
            turn_test=config.augment_rotate,
            views=config.val_views,
        )
        if len(self.train_set) == 0:
            raise DataError(f"{data_dir}: the train split is empty")
        if val_dir is not None and len(self.val_set) == 0:
            raise DataError(
                f"the validation data set {val_dir} has no shapes in its val split; name one "
                "with validation shapes (or validate on the training data set's val split)"
            )
        n_points = int(self.train_set.n_points)
        if config.n_points is not None and config.n_points != n_points:
            raise ConfigError(
                f"n_points is {config.n_points} but the clouds in {data_dir} have {n_points} points"
            )
        self.config = config = config.replace(n_points=n_points)

        self.step = TrainingStep(config, context)
        self.generator = self.step.generator
        if state is None and config.init_from is not None:
            start_from(self.generator, config)
            self.step.restart_average()
        self.sampler = DistributedSampler(
            self.train_set,
            num_replicas=context.world_size,
            rank=context.rank,
            shuffle=True,
            seed=config.seed,
        )
        self.collate = CompletionCollate(
            multi_resolution=self.generator.multi_resolution,
            centre_targets=self.step.multi_stage,
        )
        self.epoch = 0
        self.batches_done = 0
        self.epoch_sums: dict[str, float] = {}
        self.best_metric = math.inf
        self.best_epoch: int | None = None
        self.history: list[dict[str, Any]] = []
        self.batches = EpochBatches(self.sampler, config.batch_size)
        self.steps_per_epoch = self.batches.per_epoch
        self.epochs = total_epochs(config, self.steps_per_epoch)
        self.save_schedule = SaveSchedule.parse(config.save_every)
        self._loader: DataLoader | None = None
        self._val_batches: list[dict[str, Any]] | None = None
        self._writer: CheckpointWriter | None = None
        self._say: Notes = None  # run()'s
        self._last_saved = time.monotonic()
        self._epochs_since_save = 0
        self._last_plot = -math.inf
        self._epoch_started = time.perf_counter()
        if state is not None:
            try:
                self._load_state(state)
            except (KeyError, TypeError, ValueError, RuntimeError, IndexError) as err:
                raise DataError(
                    f"{out_dir / LAST} is damaged and cannot be resumed ({type(err).__name__}: "
                    f"{str(err)[:200]})"
                ) from None

    @property
    def global_step(self) -> int:
        """Optimiser steps taken so far in the run."""
        return self.epoch * self.steps_per_epoch + self.batches_done

    # -- data --------------------------------------------------------------------------

    def _train_loader(self) -> DataLoader:
        """The training loader, made once: its workers live for the whole run."""
        if self._loader is None:
            workers = self.config.workers
            self._loader = DataLoader(
                self.train_set,
                batch_sampler=self.batches,
                num_workers=workers,
                collate_fn=self.collate,
                worker_init_fn=ignore_stop_signals if workers else None,
                multiprocessing_context=start_helpers(["pfnet.training.loop"]) if workers else None,
                persistent_workers=workers > 0,
                pin_memory=self.device.type == "cuda",
            )
        return self._loader

    def _close_loader(self) -> None:
        """Stop the data-loader workers."""
        loader, self._loader = self._loader, None
        iterator = getattr(loader, "_iterator", None)
        if iterator is not None and hasattr(iterator, "_shutdown_workers"):
            iterator._shutdown_workers()

    def _validation_batches(self) -> list[dict[str, Any]]:
        """This rank's validation batches, built once (the test protocol is deterministic)."""
        if self._val_batches is None:
            self._val_batches = validation_batches(
                self.val_set, self.context, self.config.batch_size, self.collate.multi_resolution
            )
        return self._val_batches

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
            "data": self.data_identity,
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

    def _save_last(self) -> None:
        """Queue ``last.pt`` (rank 0): a snapshot now, written on the writer's thread."""
        self._last_saved = time.monotonic()
        self._epochs_since_save = 0
        if self.context.is_main and self._writer is not None:
            self._writer.submit(self.out_dir / LAST, cpu_snapshot(self._state()))

    def _best_state(self, row: dict[str, Any]) -> dict[str, Any]:
        """What ``best.pt`` holds: what inference needs, no optimiser states."""
        return cpu_snapshot(
            {
                "config": self.config.to_dict(),
                "model": self.step.scored.state_dict(),
                "epoch": self.epoch,
                "best_metric": self.best_metric,
                "metrics": dict(row),
            }
        )

    # -- validation ----------------------------------------------------------------------

    def validate(self) -> dict[str, float]:
        """Metrics on the val split (test protocol), ×1000: ``val_*`` of the scored generator.

        With a weight average (``ema``) the scored generator is the average, and the live
        weights are scored too, as ``val_live_*``: the two curves of one training trajectory.
        Empty when the val split is empty.
        """
        metrics = self._score(self.step.scored, "val_")
        if self.step.average is not None and metrics:
            metrics.update(self._score(self.generator, "val_live_"))
        return metrics

    def _score(self, network: torch.nn.Module, prefix: str) -> dict[str, float]:
        batches = self._validation_batches()
        return score_generator(
            network, batches, self.device, self.step.autocast, self.context, prefix
        )

    # -- the loop ------------------------------------------------------------------------

    def run(
        self, progress: bool = False, notes: Notes = None, say: Notes = None, on_stop: OnStop = None
    ) -> dict[str, Any]:
        """Train until ``config.epochs`` or a stop request; see :func:`train`."""
        self._say = say
        ctx = self.context
        c = self.config
        if ctx.is_main:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            with atomic_path(self.out_dir / "config.json") as tmp:
                tmp.write_text(json.dumps(c.to_dict(), indent=2) + "\n")
            note = schedule_note(c, self.steps_per_epoch)
            if note and notes is not None and self.epoch == 0 and not self.batches_done:
                notes(note)
        interrupted = False
        with StopRequest(on_stop).installed() as stop, CheckpointWriter() as writer:
            self._writer = writer
            try:
                if not self.history:
                    # Epoch 0: the untrained model, the reference the curves start from.
                    self.history.append({"epoch": 0, **self.validate()})
                self._epoch_started = time.perf_counter()
                while self.epoch < self.epochs and not interrupted:
                    interrupted = self._run_epoch(stop, progress)
                    if not interrupted and self.epoch < self.epochs:
                        # A stop requested during validation or bookkeeping: the epoch is
                        # complete; save it and end.
                        interrupted = distributed.any_rank(stop.requested, ctx)
                self._save_last()
                if ctx.is_main:
                    write_log(self.out_dir / LOG, self.history)
                    plot_curves(self.out_dir / CURVES, self.history)
                writer.flush()
            finally:
                self._close_loader()
                self._writer = None
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
            "checkpoint_write_s": round(writer.seconds_writing, 3),
        }

    def _run_epoch(self, stop: StopRequest, progress: bool) -> bool:
        """Train one epoch (or its rest); returns True if it stopped on request."""
        c, ctx = self.config, self.context
        epoch = self.epoch
        alpha = alpha_at(c, epoch, self.global_step)
        self.batches.set_epoch(epoch, skip=self.batches_done)
        loader = self._train_loader()
        total = len(loader) + self.batches_done
        train_s = 0.0
        bar = tqdm(
            total=total,
            initial=self.batches_done,
            desc=f"epoch {epoch + 1}/{self.epochs}",
            disable=not progress,
            leave=False,
            dynamic_ncols=True,
        )
        with bar:
            for batch in loader:
                started = time.perf_counter()
                alpha = alpha_at(c, epoch, self.global_step)
                self.step.batchnorm_frozen = batchnorm_frozen(c, epoch, self.global_step)
                losses = self.step(batch, alpha)  # float() of the losses waits for the GPU
                self.step.end_step()
                train_s += time.perf_counter() - started
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
                    return True
                if c.steps is not None and self.global_step >= c.steps:
                    break  # the run's last, partial epoch
                since = time.monotonic() - self._last_saved
                if self.save_schedule.due(since, self._epochs_since_save, at_epoch_end=False):
                    self._save_last()

        row = {"epoch": epoch + 1, "step": self.global_step, "lr": self.step.lr, "alpha": alpha}
        row.update(distributed.epoch_means(self.epoch_sums, self.context))
        self.step.end_epoch()
        started = time.perf_counter()
        row.update(self.validate())
        val_s = time.perf_counter() - started
        now = time.perf_counter()
        # time_s: wall time since the previous epoch ended (data loading, logging and
        # checkpoint hand-offs included); compute_s: the training and validation steps.
        row["time_s"] = round(now - self._epoch_started, 3)
        row["compute_s"] = round(train_s + val_s, 3)
        row["train_s"] = round(train_s, 3)
        self._epoch_started = now
        self.history.append(row)
        self.epoch += 1
        self.batches_done = 0
        self.epoch_sums = {}
        self._epochs_since_save += 1
        # Without validation shapes, best.pt follows the training Chamfer loss.
        metric = row.get(VAL_METRIC, row["cd_detail"])
        improved = metric < self.best_metric
        if improved:
            self.best_metric = metric
            self.best_epoch = epoch + 1
            if ctx.is_main and self._writer is not None:
                self._writer.submit(self.out_dir / BEST, self._best_state(row))
        since = time.monotonic() - self._last_saved
        if self.save_schedule.due(since, self._epochs_since_save, at_epoch_end=True):
            self._save_last()
        if ctx.is_main:
            write_log(self.out_dir / LOG, self.history)
            if time.monotonic() - self._last_plot >= CURVES_EVERY_S:
                plot_curves(self.out_dir / CURVES, self.history)
                self._last_plot = time.monotonic()
            if self._say is not None:
                keys = ("loss_g", "loss_d", "cd_detail", VAL_METRIC)
                self._say(epoch_line(epoch + 1, self.epochs, row, keys, improved))
        return False
