"""Running a whole study: prepare the data once, train and score every run, write results.json."""

from __future__ import annotations

import datetime
import json
import os
import platform
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from pfnet.errors import DataError
from pfnet.processes import threads_per_process
from pfnet.study.aggregate import summarize_settings
from pfnet.study.figures import plot_curves, render_comparison
from pfnet.study.report import SOURCE_TITLES, render_report
from pfnet.study.runs import (
    STUDY_MODELS,
    STUDY_RATIOS,
    STUDY_SEEDS,
    StudyRun,
    evaluate_run,
    study_config,
    study_runs,
    train_run,
)


def _quiet(_line: str) -> None:
    """The default of ``log`` and ``warn``: a library call prints nothing."""


def reproduce(
    out: Path,
    *,
    source: Path | None,
    data: Path | None = None,
    preset: str,
    device: str,
    seeds: Sequence[int] = STUDY_SEEDS,
    data_seed: int = 0,
    models: Sequence[str] = STUDY_MODELS,
    ratios: Sequence[float] = STUDY_RATIOS,
    overrides: dict[str, Any] | None = None,
    gallery_count: int = 5,
    lengths: Sequence[int] | None = None,
    train_data: Path | None = None,
    jobs: int = 1,
    log: Callable[[str], None] = _quiet,
    warn: Callable[[str], None] = _quiet,
) -> dict[str, Any]:
    """Run the study into ``out`` (see the module docstring); returns ``results.json``.

    ``lengths`` sizes every run in optimiser steps instead of the schedule's epochs, each
    setting trained once per length (``[N, 2N]``: the twice-the-steps test). ``train_data``
    trains every run on that data set's train split (validation and test stay ``data``'s).
    ``jobs`` runs up to that many trainings side by side, each in its own process, on the
    one device (a small network's step leaves most of a GPU idle).

    ``log`` is called with each line of the study's progress, ``warn`` with the error of a run
    that failed in a process of its own (``pfnet reproduce`` prints them); with ``jobs > 1``
    they go to those processes, so they must be functions of a module (or ``print``).
    """
    from pfnet.data import prepare_dataset, read_manifest

    base = study_config(preset, **(overrides or {}))
    data_dir = data if data is not None else out / "data"
    if not (data_dir / "manifest.json").is_file():
        if data is not None:
            raise DataError(f"{data} is not a prepared data set (no manifest.json)")
        log(f"preparing the data set from {source or 'procedural shapes'} into {data_dir}")
        report = prepare_dataset(source, data_dir, seed=data_seed, progress=None)
        log(report.summary())
    manifest = read_manifest(data_dir)
    # Each run keeps its best validation epoch and the study draws the validation curves, so
    # an empty validation split would fail only after the first training (and test: scores).
    empty = [name for name in ("val", "test") if not manifest["splits"].get(name, {}).get("total")]
    if empty:
        raise DataError(
            f"data set {data_dir} has no shapes in its {' or '.join(empty)} split; the study "
            "tests each run's best validation epoch on the test split. Prepare it again with "
            "a larger validation (or test) fraction, or with more shapes per category"
        )

    train_manifest = None
    if train_data is not None:
        if not (train_data / "manifest.json").is_file():
            raise DataError(f"{train_data} is not a prepared data set (no manifest.json)")
        train_manifest = read_manifest(train_data)
        if not train_manifest["splits"].get("train", {}).get("total"):
            raise DataError(f"training data set {train_data} has no shapes in its train split")
        if train_manifest["points"] != manifest["points"]:  # before hours of training
            raise DataError(
                f"training data set {train_data} holds clouds of {train_manifest['points']} "
                f"points, the study's data set {data_dir} clouds of {manifest['points']}: a "
                "model trained on one cannot be tested on the other"
            )

    records = []
    runs = study_runs(models, ratios, seeds, list(lengths) if lengths else [None])
    run_threads = None  # each run's torch threads when they are not this process's
    if jobs > 1:
        run_threads = train_side_by_side(
            runs, base, data_dir, out / "runs", device, jobs, train_data, log, warn
        )
    for k, run in enumerate(runs, 1):
        run_dir = out / "runs" / run.name
        prefix = f"[{k}/{len(runs)}] "
        train_run(
            run, base, data_dir, run_dir, device, lambda msg, p=prefix: log(p + msg), train_data
        )
        t0 = time.monotonic()
        records.append(evaluate_run(run, data_dir, run_dir, device))
        records[-1]["eval_time_s"] = round(time.monotonic() - t0, 1)
        log(
            f"{run.name}: missing Pred→GT {records[-1]['missing']['mean']['pred_to_gt']:.3f} "
            f"GT→Pred {records[-1]['missing']['mean']['gt_to_pred']:.3f} (×1000)"
        )

    config = base.to_dict()
    del config["seed"]  # each run has its own; see "seeds"
    results = {
        "format": "pfnet-results",
        "version": 2,
        "created": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "machine": _machine(device, run_threads),
        "dataset": _dataset_summary(manifest),
        **({} if train_manifest is None else {"train_dataset": _dataset_summary(train_manifest)}),
        "preset": preset,
        "config": config,
        "seeds": list(seeds),
        "runs": records,
        "settings": summarize_settings(records),
        # Training and evaluation of every run, whichever calls did them.
        "study_time_s": round(sum(r["train_time_s"] + r["eval_time_s"] for r in records), 1),
    }
    write_results(out, results, data_dir, gallery_count)
    return results


def train_side_by_side(
    runs: Sequence[StudyRun],
    base: Any,
    data_dir: Path,
    runs_dir: Path,
    device: str,
    jobs: int,
    train_data: Path | None,
    log: Callable[[str], None],
    warn: Callable[[str], None],
) -> int:
    """Train ``runs`` with up to ``jobs`` processes at a time (each :func:`train_run`).

    The host's cores are shared out: each process gets ``cores // jobs`` torch threads (at
    least one), not torch's default of one per core, which makes processes spin-wait on each
    other's threads. Returns that number of threads.

    Each process is a fresh interpreter (spawned), so CUDA and the data loaders' workers
    start cleanly in it. Ctrl-C reaches every process: each saves its ``last.pt`` and the
    next call resumes them. A run that fails stops the study once the others have finished,
    naming the run; its own error is above, in its output.
    """
    import multiprocessing

    context = multiprocessing.get_context("spawn")
    threads = threads_per_process(min(jobs, len(runs)))
    log(f"{min(jobs, len(runs))} runs at a time, {threads} torch thread(s) each")
    waiting = list(enumerate(runs, 1))
    running: list[tuple[str, Any]] = []
    failed = []
    try:
        while waiting or running:
            while waiting and len(running) < jobs:
                k, run = waiting.pop(0)
                process = context.Process(
                    target=_train_in_process,
                    args=(
                        run,
                        base,
                        data_dir,
                        runs_dir / run.name,
                        device,
                        train_data,
                        f"[{k}/{len(runs)}] ",
                        threads,
                        log,
                        warn,
                    ),
                    name=run.name,
                )
                process.start()
                running.append((run.name, process))
            for name, process in list(running):
                process.join(timeout=0.2)
                if process.exitcode is not None:
                    running.remove((name, process))
                    if process.exitcode != 0:
                        failed.append(name)
    except KeyboardInterrupt:
        try:
            for _, process in running:  # each saves its last.pt on the same Ctrl-C
                process.join()
        except KeyboardInterrupt:  # a second Ctrl-C: abort them (last.pt files stay whole)
            for _, process in running:
                process.kill()
            for _, process in running:
                process.join()
        raise
    if failed:
        raise DataError(
            f"training failed for {', '.join(failed)} (exit codes above); the other runs are "
            "kept, and running the study again resumes where it stopped"
        )
    return threads


def _train_in_process(
    run: StudyRun,
    base: Any,
    data_dir: Path,
    run_dir: Path,
    device: str,
    train_data: Path | None,
    prefix: str,
    threads: int,
    log: Callable[[str], None] = _quiet,
    warn: Callable[[str], None] = _quiet,
) -> None:
    """One run of :func:`train_side_by_side` in its own process, on ``threads`` torch threads
    (:func:`pfnet.processes.threads_per_process`); its exit code says how it went, ``log``
    hears its progress and ``warn`` its error."""
    import sys

    import torch

    from pfnet.errors import PfnetError

    torch.set_num_threads(threads)

    try:
        train_run(
            run,
            base,
            data_dir,
            run_dir,
            device,
            lambda msg: log(prefix + msg),
            train_data,
            progress=False,
        )
    except KeyboardInterrupt:
        sys.exit(130)
    except (PfnetError, OSError, MemoryError) as err:  # the CLI's one-line errors
        warn(f"{prefix}{run.name}: error: {err}")
        sys.exit(1)


def _machine(device: str, threads: int | None = None) -> dict[str, Any]:
    """The machine of the study; ``threads``: each run's torch threads if not this process's."""
    import torch

    name = platform.processor() or platform.machine()
    if device.startswith("cuda"):
        name = torch.cuda.get_device_name(torch.device(device))
    return {
        "device": device.split(":")[0],
        "name": name,
        "cpu_count": os.cpu_count(),
        "torch_threads": threads or torch.get_num_threads(),
        "torch": torch.__version__.split("+")[0],
        "python": platform.python_version(),
    }


def _dataset_summary(manifest: dict[str, Any]) -> dict[str, Any]:
    splits = manifest["splits"]
    source = manifest.get("source") or {}
    title = SOURCE_TITLES.get(source.get("format"))
    if title is None:  # the open-shapes sources, or several of them: their catalogues' names
        licences = manifest.get("licenses") or []
        title = " and ".join(x["catalogue"] for x in licences if x.get("catalogue"))
        if not title or len(title) > 200:  # the record's limit: the sources' short names
            title = " and ".join(str(x.get("source")) for x in licences) or source.get("format")
    return {
        "source": title,
        "points": manifest["points"],
        "splits": {name: split["total"] for name, split in splits.items()},
        "credits": [
            f"{x.get('catalogue')} ({x.get('license')})" for x in manifest.get("licenses") or []
        ],
    }


def write_results(out: Path, results: dict[str, Any], data_dir: Path, gallery_count: int) -> None:
    """Write ``results.json``, ``results.md``, ``curves.png`` and ``gallery.png`` into ``out``."""
    from pfnet.io.files import atomic_path

    with atomic_path(out / "results.json") as tmp:
        tmp.write_text(json.dumps(results, indent=1) + "\n")
    plot_curves(out / "curves.png", results)
    render_comparison(out / "gallery.png", results, out / "runs", data_dir, gallery_count)
    with atomic_path(out / "results.md") as tmp:
        tmp.write_text(render_report(results))


def rewrite_report(out: Path, results: dict[str, Any], data_dir: Path, gallery_count: int) -> None:
    """Rebuild ``out``'s report from ``results``: the figures too if the runs and data are there."""
    from pfnet.io.files import atomic_path

    if (out / "runs").is_dir() and (data_dir / "manifest.json").is_file():
        write_results(out, results, data_dir, gallery_count)
    else:
        with atomic_path(out / "results.md") as tmp:
            tmp.write_text(render_report(results))
