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
from pfnet.study.aggregate import summarize_settings
from pfnet.study.figures import plot_curves, render_comparison
from pfnet.study.report import SOURCE_TITLES, render_report
from pfnet.study.runs import (
    STUDY_MODELS,
    STUDY_RATIOS,
    STUDY_SEEDS,
    evaluate_run,
    study_config,
    study_runs,
    train_run,
)


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
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Run the study into ``out`` (see the module docstring); returns ``results.json``."""
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

    records = []
    runs = study_runs(models, ratios, seeds)
    for k, run in enumerate(runs, 1):
        run_dir = out / "runs" / run.name
        prefix = f"[{k}/{len(runs)}] "
        train_run(run, base, data_dir, run_dir, device, lambda msg, p=prefix: log(p + msg))
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
        "machine": _machine(device),
        "dataset": _dataset_summary(manifest),
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


def _machine(device: str) -> dict[str, Any]:
    import torch

    name = platform.processor() or platform.machine()
    if device.startswith("cuda"):
        name = torch.cuda.get_device_name(torch.device(device))
    return {
        "device": device.split(":")[0],
        "name": name,
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "torch": torch.__version__.split("+")[0],
        "python": platform.python_version(),
    }


def _dataset_summary(manifest: dict[str, Any]) -> dict[str, Any]:
    splits = manifest["splits"]
    source = manifest.get("source") or {}
    return {
        "source": SOURCE_TITLES.get(source.get("format"), source.get("format")),
        "points": manifest["points"],
        "splits": {name: split["total"] for name, split in splits.items()},
        "credits": [
            f"{x.get('catalogue')} ({x.get('license')})" for x in manifest.get("licenses") or []
        ],
    }


def write_results(out: Path, results: dict[str, Any], data_dir: Path, gallery_count: int) -> None:
    """Write ``results.json``, ``results.md``, ``curves.png`` and ``gallery.png`` into ``out``."""
    from pfnet.io import atomic_path

    with atomic_path(out / "results.json") as tmp:
        tmp.write_text(json.dumps(results, indent=1) + "\n")
    plot_curves(out / "curves.png", results)
    render_comparison(out / "gallery.png", results, out / "runs", data_dir, gallery_count)
    with atomic_path(out / "results.md") as tmp:
        tmp.write_text(render_report(results))


def rewrite_report(out: Path, results: dict[str, Any], data_dir: Path, gallery_count: int) -> None:
    """Rebuild ``out``'s report from ``results``: the figures too if the runs and data are there."""
    from pfnet.io import atomic_path

    if (out / "runs").is_dir() and (data_dir / "manifest.json").is_file():
        write_results(out, results, data_dir, gallery_count)
    else:
        with atomic_path(out / "results.md") as tmp:
            tmp.write_text(render_report(results))
