"""Reading a study's ``results.json`` back, checked to be a record ``pfnet reproduce`` writes.

``--report-only`` rebuilds the report and the figures from this file, which is published and
may be edited or forged. It is checked here once, whole, with exact types: the tables and the
figures then only ever see a well-formed record of a study pfnet could have run.
"""

from __future__ import annotations

import json
import math
import stat
from pathlib import Path
from typing import Any

from pfnet.errors import DataError
from pfnet.study.aggregate import summarize_settings
from pfnet.study.runs import (
    BASE_RATIO,
    MAX_LENGTHS,
    MAX_RATIOS,
    MAX_RUNS,
    MAX_SEEDS,
    STUDY_MODELS,
    study_runs,
)
from pfnet.training.config import MAX_STEPS

# A study of MAX_RUNS runs is a few MB; the cap only keeps the JSON parser's memory bounded.
MAX_RESULTS_BYTES = 64 << 20


# The most epochs a run's curve may list (the paper trains 200).
MAX_EPOCHS = 100_000


class _Malformed(ValueError):
    """A problem with the record, said in a few words."""


def _need(condition: bool, problem: str) -> None:
    if not condition:
        raise _Malformed(problem)


def _is_int(value: Any) -> bool:
    return type(value) is int


def _is_number(value: Any) -> bool:
    return type(value) in (int, float) and math.isfinite(value)


def _int(record: dict[str, Any], key: str, where: str, low: int = 0) -> int:
    value = record.get(key)
    _need(_is_int(value) and value >= low, f"{where}: {key} must be an integer >= {low}")
    return value


def _number(record: dict[str, Any], key: str, where: str) -> float:
    value = record.get(key)
    _need(_is_number(value) and value >= 0, f"{where}: {key} must be a finite number >= 0")
    return value


def _string(record: dict[str, Any], key: str, where: str) -> str:
    value = record.get(key)
    _need(isinstance(value, str), f"{where}: {key} must be a string")
    return value


def _object(value: Any, where: str) -> dict[str, Any]:
    _need(isinstance(value, dict), f"{where} must be a JSON object")
    return value


def _metrics(value: Any, where: str, keys: set[str] | None) -> set[str]:
    """Check a row of metrics (``pred_to_gt``, ``gt_to_pred``, ...; ``n`` a count)."""
    row = _object(value, where)
    for key, number in row.items():
        if key == "n":
            _need(_is_int(number) and number >= 0, f"{where}: n must be an integer >= 0")
        else:
            _need(_is_number(number), f"{where}: {key} must be a finite number")
    _need({"pred_to_gt", "gt_to_pred"} <= row.keys(), f"{where} lacks pred_to_gt or gt_to_pred")
    _need(keys is None or row.keys() == keys, f"{where} has other metrics than the first run")
    return set(row.keys())


def _region(run: dict[str, Any], region: str, where: str, first: dict[str, Any] | None) -> None:
    """Check a run's ``missing`` or ``whole`` scores against the first run's layout."""
    where = f"{where}.{region}"
    scores = _object(run.get(region), where)
    categories = _object(scores.get("categories"), f"{where}.categories")
    _need(categories, f"{where}.categories is empty")
    if first is not None:
        _need(categories.keys() == first[region]["categories"].keys(), f"{where}: other categories")
    for name, row in categories.items():
        known = None if first is None else set(first[region]["categories"][name])
        _need("n" in _object(row, f"{where}.categories.{name}"), f"{where}.{name} lacks n")
        _metrics(row, f"{where}.categories.{name}", known)
    _metrics(
        scores.get("mean"), f"{where}.mean", None if first is None else set(first[region]["mean"])
    )


def _curve(run: dict[str, Any], where: str) -> None:
    """Check a run's validation curve: epochs 1, 2, ... and one finite value each."""
    curve = _object(run.get("curve"), f"{where}.curve")
    epochs, values = curve.get("epoch"), curve.get("val_cd_l2")
    detail = curve.get("train_cd_detail")
    n = run["epochs"]
    _need(
        isinstance(epochs, list) and epochs == list(range(1, n + 1)),
        f"{where}.curve.epoch must list the epochs 1 to {n}",
    )
    _need(
        isinstance(values, list) and len(values) == n and all(map(_is_number, values)),
        f"{where}.curve.val_cd_l2 must hold a finite number for each of the {n} epochs",
    )
    _need(
        isinstance(detail, list)
        and len(detail) == n
        and all(v is None or _is_number(v) for v in detail),
        f"{where}.curve.train_cd_detail must hold a number or null for each of the {n} epochs",
    )
    _need(run["best_epoch"] <= n, f"{where}: best_epoch is after the last epoch")


def _plateau(run: dict[str, Any], where: str) -> None:
    plateau = _object(run.get("plateau"), f"{where}.plateau")
    _int(plateau, "window", f"{where}.plateau")
    gain = plateau.get("gain")
    _need(gain is None or _is_number(gain), f"{where}.plateau.gain must be a number or null")
    _need(type(plateau.get("levelled")) is bool, f"{where}.plateau.levelled must be true or false")


def _run(run: Any, where: str, first: dict[str, Any] | None) -> None:
    """Check one run's record (``evaluate_run``)."""
    run = _object(run, where)
    _need(
        run.get("model") in STUDY_MODELS, f"{where}: model must be one of {', '.join(STUDY_MODELS)}"
    )
    ratio = run.get("missing_ratio")
    _need(
        type(ratio) is float and 0.0 < ratio < 1.0,
        f"{where}: missing_ratio must be a number in (0, 1)",
    )
    _need(_is_int(run.get("seed")), f"{where}: seed must be an integer")
    if "steps" in run:  # a study sized in steps (reproduce --steps)
        _int(run, "steps", where, low=1)
        _need(run["steps"] <= MAX_STEPS, f"{where}: more than {MAX_STEPS:,} steps")
    for key in ("name", "setting"):
        _string(run, key, where)
    _int(run, "n_missing", where, low=1)
    _int(run, "parameters", where)
    _int(run, "epochs", where, low=1)
    _need(run["epochs"] <= MAX_EPOCHS, f"{where}: more than {MAX_EPOCHS:,} epochs")
    _int(run, "best_epoch", where, low=1)
    for key in ("train_time_s", "epoch_time_s", "eval_time_s", "best_val_cd_l2"):
        _number(run, key, where)
    _curve(run, where)
    _plateau(run, where)
    for region in ("missing", "whole"):
        _region(run, region, where, first)


def _dataset(value: Any, where: str) -> None:
    """Check a data set's summary (``_dataset_summary``)."""
    data = _object(value, where)
    source = _string(data, "source", where)
    _need(  # written into the report as it is
        source.isprintable() and len(source) <= 200,
        f"{where}.source must be printable text of at most 200 characters",
    )
    _int(data, "points", where, low=1)
    splits = _object(data.get("splits"), f"{where}.splits")
    _need(
        all(_is_int(n) and n >= 0 for n in splits.values()),
        f"{where}.splits: counts must be integers",
    )
    credits = data.get("credits", [])
    _need(
        isinstance(credits, list) and all(isinstance(c, str) for c in credits),
        f"{where}.credits must be a list of strings",
    )


def _header(results: dict[str, Any]) -> None:
    """Check what the report says of the study as a whole."""
    _need(results.get("format") == "pfnet-results", 'format must be "pfnet-results"')
    _need(results.get("version") == 2, "version must be 2 (this pfnet writes version 2)")
    _string(results, "preset", "the record")
    _number(results, "study_time_s", "the record")
    for key in ("dataset", "train_dataset"):
        if key == "dataset" or key in results:  # train_dataset: reproduce --train-data
            _dataset(results.get(key), key)
    machine = _object(results.get("machine"), "machine")
    for key in ("device", "name", "torch"):
        _string(machine, key, "machine")
    _int(machine, "torch_threads", "machine", low=1)
    config = _object(results.get("config"), "config")
    for key in ("width", "lr", "lr_gamma"):
        _number(config, key, "config")
    for key in ("batch_size", "lr_step", "epochs"):
        _int(config, key, "config", low=1)


def check_results(results: Any) -> None:
    """Check that ``results`` is a record of a study ``pfnet reproduce`` could have run.

    Besides the types of every field the tables and figures use, the runs must be exactly
    the study's runs (:func:`~pfnet.study.runs.study_runs`) of their models, ratios and seeds,
    within the study's bounds (:data:`~pfnet.study.runs.MAX_RUNS`), and the settings must be
    those runs combined over the seeds.

    Raises:
        ValueError: What is wrong, in a few words.
    """
    results = _object(results, "the record")
    runs, seeds = results.get("runs"), results.get("seeds")
    _need(isinstance(runs, list) and runs, "runs must be a non-empty list")
    _need(len(runs) <= MAX_RUNS, f"{len(runs):,} runs; a study has at most {MAX_RUNS}")
    _need(
        isinstance(seeds, list)
        and 1 <= len(seeds) <= MAX_SEEDS
        and all(map(_is_int, seeds))
        and len(set(seeds)) == len(seeds),
        f"seeds must be a list of 1 to {MAX_SEEDS} different integers",
    )
    _header(results)
    for k, run in enumerate(runs):
        _run(run, f"runs[{k}]", runs[0] if k else None)
    first = [r for r in runs if r["seed"] == seeds[0]]
    models = list(dict.fromkeys(r["model"] for r in first if r["missing_ratio"] == BASE_RATIO))
    ratios = [BASE_RATIO] + list(
        dict.fromkeys(
            r["missing_ratio"]
            for r in first
            if r["model"] == "pfnet" and r["missing_ratio"] != BASE_RATIO
        )
    )
    _need(
        len(ratios) <= MAX_RATIOS, f"{len(ratios)} missing ratios; a study has at most {MAX_RATIOS}"
    )
    lengths = list(dict.fromkeys(r.get("steps") for r in first))
    _need(
        lengths == [None] or None not in lengths,
        "runs must all have steps (a study sized in steps) or none",
    )
    _need(len(lengths) <= MAX_LENGTHS, f"{len(lengths)} run lengths; at most {MAX_LENGTHS}")
    expected = [
        (r.name, r.setting, r.model, r.missing_ratio, r.seed, r.steps)
        for r in study_runs(models, ratios, seeds, lengths)
    ]
    found = [
        (r["name"], r["setting"], r["model"], r["missing_ratio"], r["seed"], r.get("steps"))
        for r in runs
    ]
    _need(
        found == expected,
        "the runs are not those of a study of their models, ratios and seeds "
        f"(expected {', '.join(e[0] for e in expected[:8])}{', ...' if len(expected) > 8 else ''})",
    )
    _need(
        results.get("settings") == summarize_settings(runs),
        "settings are not the runs combined over the seeds",
    )


def read_results(path: Path) -> dict[str, Any]:
    """A study's ``results.json``, checked by :func:`check_results`.

    Raises:
        DataError: If it cannot be read or is not a record of a study pfnet could have run;
            the message names the file and the problem.
    """
    try:
        if not stat.S_ISREG(path.stat().st_mode):
            raise ValueError("not a regular file")
        with open(path, "rb") as file:
            data = file.read(MAX_RESULTS_BYTES + 1)
        if len(data) > MAX_RESULTS_BYTES:
            raise ValueError(f"larger than {MAX_RESULTS_BYTES >> 20} MB, not a study record")
        results = json.loads(data)
        if not isinstance(results, dict) or not isinstance(results.get("runs"), list):
            raise ValueError("not a study record (no list of runs)")
    except (OSError, ValueError, RecursionError) as err:
        raise DataError(f"cannot read {path}: {str(err)[:200]}") from None
    try:
        check_results(results)
    except _Malformed as err:
        raise DataError(f"{path} is not a study record this pfnet can report: {err}") from None
    return results
