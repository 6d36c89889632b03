"""The demo: the whole pipeline on real data in a few minutes on a CPU (``pfnet demo``).

1. Build a data set from Debian's SweetHome3D furniture (``sweethome3d-furniture``, real
   CC-BY/CC0 models); if it is not installed, say how to install it and use procedural
   shapes instead.
2. Train the ``small`` preset of PF-Net for a time budget (``minutes``): two epochs are
   trained and the second one timed (the first pays for start-up), then the run is resumed
   for as many epochs as fit in the rest of the budget.
3. Predict the test split with the deterministic test protocol, evaluate it (Chamfer ×1000,
   F-score), and do the same with the shipped default model (trained for hours on the
   training split of the same catalogues; the test split is one it has never seen).
4. Render a gallery PNG: each test sample's input, the short run's completion, the shipped
   model's completion and the ground truth.

Everything goes under the output folder; running the demo again reuses the data set if it is there.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pfnet.data import SWEETHOME3D_PATH
from pfnet.data.sources import pick_source
from pfnet.errors import ConfigError, DataError

SWEETHOME3D_FURNITURE: Path = SWEETHOME3D_PATH
INSTALL_HINT = "sudo apt-get install sweethome3d-furniture"
MAX_MINUTES = 7 * 24 * 60
"""The longest time budget: a week."""


def _quiet(_line: str) -> None:
    """The default of ``say``: a library call prints nothing."""


def choose_source(
    source: Path | None, *, procedural: bool = False, say: Callable[[str], None] = _quiet
) -> Path | None:
    """The model folder to use, or None for procedural shapes (with a hint to ``say``)."""
    return pick_source(
        source, procedural=procedural, default=SWEETHOME3D_FURNITURE, hint=INSTALL_HINT, say=say
    )


def fresh_folder(path: Path) -> Path:
    """``path`` if it does not exist yet, else the first free ``path-2``, ``path-3``, ..."""
    candidate, k = path, 1
    while candidate.exists():
        k += 1
        candidate = path.with_name(f"{path.name}-{k}")
    return candidate


def comparison_table(run: dict, shipped: dict) -> str:
    """The mean metrics of the short run beside the shipped model's, as text."""
    lines = ["                  Pred→GT  GT→Pred  F-score@0.01   (missing region, ×1000)"]
    for label, mean in (("this run", run), ("shipped model", shipped)):
        lines.append(
            f"  {label:<15}{mean['pred_to_gt']:8.3f} {mean['gt_to_pred']:8.3f} "
            f"{mean['f_score']:13.3f}"
        )
    return "\n".join(lines)


def find_checkpoint(run_dir: Path) -> Path:
    """The best checkpoint of a training run (``best.pt``, else ``last.pt``)."""
    for name in ("best.pt", "last.pt"):
        if (run_dir / name).is_file():
            return run_dir / name
    raise ConfigError(f"training wrote no checkpoint (best.pt or last.pt) in {run_dir}")


def epochs_for_budget(left_s: float, epoch_s: float, preset_epochs: int) -> int:
    """Epochs in all after the two timed ones, given the seconds left and an epoch's cost.

    Fills the budget (validation still improves at the small preset's 30 epochs on
    SweetHome3D), up to three times the preset's schedule; at least the 2 already trained.
    """
    more = math.floor(left_s / max(epoch_s, 1e-3)) if left_s > 0 else 0
    return max(2, min(3 * preset_epochs, 2 + more))


@dataclass
class DemoResult:
    """What :func:`run_demo` made and where (the command prints it).

    Attributes:
        out: The demo's folder.
        minutes: Wall time of the whole demo.
        data_dir: The data set, and ``source`` the text of where it came from.
        checkpoint: The trained run's best checkpoint.
        pred_dir: The run's predictions of the test split.
        metrics: ``metrics.json`` of the run, and ``mean`` its mean metrics (×1000).
        shipped_metrics: ``metrics-shipped.json``, and ``shipped_mean``, when the shipped
            model was compared; else None.
        gallery: The gallery picture.
        licences: The data set's licence entries (catalogue, licence, creators).
    """

    out: Path
    minutes: float
    data_dir: Path
    source: str
    checkpoint: Path
    pred_dir: Path
    metrics: Path
    mean: dict[str, float]
    gallery: Path
    shipped_metrics: Path | None = None
    shipped_mean: dict[str, float] | None = None
    licences: list[dict[str, Any]] = field(default_factory=list)


def shipped_comparison(
    data_dir: Path, points: int, say: Callable[[str], None] = _quiet
) -> Path | None:
    """The default shipped model's file if it completes clouds of this data set's size."""
    from pfnet.inference.shipped import DEFAULT_MODEL, SUFFIX, WEIGHTS_DIR, read_metadata

    path = WEIGHTS_DIR / f"{DEFAULT_MODEL}{SUFFIX}"
    if not path.is_file():
        say(f"no shipped model {DEFAULT_MODEL} in this installation; skipping the comparison")
        return None
    config, _ = read_metadata(path)
    if config.get("n_points") != points:
        say(
            f"the shipped model {DEFAULT_MODEL} takes {config.get('n_points')}-point clouds, "
            f"this data set has {points}; skipping the comparison"
        )
        return None
    return path


def run_demo(
    out: Path,
    *,
    minutes: float = 5.0,
    epochs: int | None = None,
    source: Path | None = None,
    procedural: bool = False,
    points: int = 2048,
    count: int | None = None,
    device: str = "cpu",
    seed: int = 0,
    gallery_count: int = 6,
    say: Callable[[str], None] = _quiet,
) -> DemoResult:
    """Run the demo into ``out`` (see the module docstring).

    Args:
        out: Output folder; a data set already in ``out/data`` is reused.
        minutes: Training time budget, filled with as many epochs as fit.
        epochs: Train exactly this many epochs instead of filling ``minutes``.
        source: Models to build the data set from (default: the SweetHome3D furniture,
            else procedural shapes).
        procedural: Use procedural shapes, not real models.
        points: Points per shape.
        count: Shapes per category of procedural data.
        device: ``auto``, ``cpu``, ``cuda`` or ``cuda:N``.
        seed: Seed of data and training.
        gallery_count: Samples in the gallery.
        say: Called with each line of the demo's progress (``pfnet demo`` prints them);
            by default nothing is printed.

    Returns:
        Where everything is, for the caller to report.

    Raises:
        ConfigError: ``minutes`` or ``epochs`` out of range, a bad device or source, or an
            output folder that is a link, a data set, a prediction folder or a training run.
    """
    if not (math.isfinite(minutes) and 0 < minutes <= MAX_MINUTES):
        raise ConfigError(f"the time budget must be positive and at most a week, got {minutes}")
    if epochs is not None and epochs < 1:
        raise ConfigError(f"epochs must be at least 1, got {epochs}")
    from pfnet.data import prepare_dataset, read_manifest
    from pfnet.evaluation.reports import format_table, write_json
    from pfnet.evaluation.scoring import evaluate_predictions
    from pfnet.inference.devices import inference_device
    from pfnet.inference.predict import predict_split
    from pfnet.inference.shipped import describe
    from pfnet.io.files import other_kind
    from pfnet.training import train
    from pfnet.training.config import preset_config
    from pfnet.training.signals import STOP_NOTICE
    from pfnet.viz.gallery import render_evaluation_gallery

    device = inference_device(device)
    out = Path(out)
    data_dir, pred_dir = out / "data", out / "predictions"
    for folder in (data_dir, pred_dir, out / "predictions-shipped", out / "run"):
        if folder.is_symlink():  # a planted link would take the demo's outputs elsewhere
            raise ConfigError(f"{folder} is a link; the demo writes only into real folders")
    kind = other_kind(out)
    if kind is not None:  # the demo's folder holds data/, run/, predictions/...: not these
        raise ConfigError(f"--out {out} is {kind}; name a folder for the demo")
    out.mkdir(parents=True, exist_ok=True)
    run_dir = fresh_folder(out / "run")
    started = time.monotonic()

    say("\n[1/6] data set")
    source = choose_source(source, procedural=procedural, say=say)
    if (data_dir / "manifest.json").is_file():
        say(f"reusing the data set in {data_dir} (delete it to rebuild)")
    else:
        say(f"building it from {source or 'procedural shapes'} into {data_dir}")
        report = prepare_dataset(
            source, data_dir, points=points, seed=seed, count=count, progress=None
        )
        say(report.summary())
    manifest = read_manifest(data_dir)
    empty = [n for n in ("train", "test") if not manifest["splits"].get(n, {}).get("total")]
    if empty:  # before minutes of training, not after them
        raise DataError(
            f"the data set {data_dir} has no shapes in its {' or '.join(empty)} split; the "
            "demo trains on one and completes the other: give it more shapes (--count)"
        )

    say(f"\n[2/6] training the small PF-Net preset on {device}")
    config = preset_config("small").replace(seed=seed)
    say(f"run folder {run_dir}")
    heard = {"say": say, "on_stop": lambda: say(f"\n{STOP_NOTICE}")}  # the training's lines
    if epochs is not None:
        train(config.replace(epochs=epochs), data_dir, run_dir, device=device, **heard)
    else:
        budget = minutes * 60.0
        t0 = time.monotonic()
        # Two epochs first: the first one pays for start-up (imports, data-loader workers,
        # CUDA initialisation), the second one's wall time is what every later epoch costs.
        summary = train(config.replace(epochs=2), data_dir, run_dir, device=device, **heard)
        per_epoch = float(summary["final"].get("time_s") or 0.0)
        total = epochs_for_budget(budget - (time.monotonic() - t0), per_epoch, config.epochs)
        say(f"an epoch takes {per_epoch:.1f} s after start-up: training {total} epochs in all")
        if total > 2:
            train(
                config.replace(epochs=total), data_dir, run_dir, device=device, resume=True, **heard
            )
    checkpoint = find_checkpoint(run_dir)

    say("\n[3/6] predicting the test split (deterministic test protocol)")
    info = predict_split(checkpoint, data_dir, pred_dir, device=device)
    ratio = info["protocol"]["missing_ratio"]

    say("\n[4/6] evaluating")
    evaluation = evaluate_predictions(pred_dir, data_dir, missing_ratio=ratio, notes=say)
    say("Pred→GT, GT→Pred, CD-L2, CD-L1 ×1000; F-score at distance 0.01 (missing region)")
    say(format_table(evaluation))
    metrics_path = out / "metrics.json"
    write_json(metrics_path, evaluation.report)

    say("\n[5/6] the shipped model on the same test split")
    shipped = shipped_comparison(data_dir, int(manifest.get("points", points)), say)
    columns = {"this run": pred_dir}
    shipped_mean = None
    if shipped is not None:
        shipped_dir = out / "predictions-shipped"
        predict_split(shipped, data_dir, shipped_dir, device=device, missing_ratio=ratio)
        shipped_eval = evaluate_predictions(shipped_dir, data_dir, missing_ratio=ratio, notes=say)
        write_json(out / "metrics-shipped.json", shipped_eval.report)
        shipped_mean = shipped_eval.report["mean"]
        columns[f"shipped {describe(shipped).removeprefix('shipped:')}"] = shipped_dir
        say(comparison_table(evaluation.report["mean"], shipped_mean))

    say("\n[6/6] rendering a gallery")
    gallery = render_evaluation_gallery(
        out / "gallery.png",
        evaluation,
        pred_dir,
        data_dir,
        split="test",
        missing_ratio=ratio,
        count=gallery_count,
        columns=columns,
    )

    return DemoResult(
        out=out,
        minutes=(time.monotonic() - started) / 60.0,
        data_dir=data_dir,
        source=str(manifest.get("source", source or "procedural")),
        checkpoint=checkpoint,
        pred_dir=pred_dir,
        metrics=metrics_path,
        mean=evaluation.report["mean"],
        gallery=Path(gallery),
        shipped_metrics=None if shipped_mean is None else out / "metrics-shipped.json",
        shipped_mean=shipped_mean,
        licences=list(manifest.get("licenses") or []),
    )
