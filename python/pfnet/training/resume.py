"""Where a run starts: what ``--resume`` checks (the same data set, a configuration changed
only where allowed), and the weights ``init_from`` fine-tunes."""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch
from torch import nn

from pfnet.errors import ConfigError, DataError
from pfnet.training.config import RESUMABLE_FIELDS, TrainConfig

# Fingerprints of another kind (the first one hashed the whole manifest) are not compared.
IDENTITY_KIND = "train-split-2"


def data_identity(data_dir: Path) -> dict[str, str]:
    """What a run records of its training data, so that ``--resume`` can refuse other data.

    The fingerprint covers what decides the training split — the manifest's source, options,
    seed, categories, pool and train-split record, and the train file's size — so a data set
    moved or copied elsewhere keeps it, and the validation data may change (``--val-data``).
    """
    manifest_path = Path(data_dir) / "manifest.json"
    try:
        manifest = json.loads(manifest_path.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):
        manifest = {}
    if not isinstance(manifest, dict):
        manifest = {}
    keys = ("source", "points", "seed", "split", "categories", "pool", "normalization")
    decisive = {key: manifest.get(key) for key in keys}
    splits = manifest.get("splits")
    decisive["train"] = splits.get("train") if isinstance(splits, dict) else None
    train = Path(data_dir) / "train.npz"
    decisive["train_bytes"] = train.stat().st_size if train.is_file() else -1
    digest = hashlib.sha256(json.dumps(decisive, sort_keys=True, default=str).encode())
    return {
        "path": str(Path(data_dir).resolve()),
        "fingerprint": digest.hexdigest(),
        "kind": IDENTITY_KIND,
    }


def resumed_config(config: TrainConfig, state: dict[str, Any], path: Path) -> TrainConfig:
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


# More epochs than any run trains: a larger stored counter is a damaged or forged file.
MAX_EPOCHS = 1_000_000


def check_resumable(state: dict[str, Any], path: Path) -> None:
    """Refuse a ``last.pt`` that is not a whole, finite training state.

    A plain model checkpoint copied over ``last.pt`` (a ``KeyError`` traceback before), NaN
    weights (a run that would train on NaN to the end with exit 0) and forged counters are
    named in one line.

    Raises:
        DataError: What is missing or wrong, naming ``path``.
    """
    needed = ("optimizer_g", "scheduler_g", "epoch", "batches_done", "epoch_sums", "history")
    missing = [key for key in (*needed, "best_metric", "rng", "world_size") if key not in state]
    if missing:
        raise DataError(
            f"{path} is not a training state to resume (no {', '.join(missing)}): "
            "a model file, or damaged"
        )
    for key in ("epoch", "batches_done", "world_size"):
        value = state[key]
        if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value <= MAX_EPOCHS:
            raise DataError(f"{path} has an impossible {key} ({value!r}): damaged or forged")
    for part in ("model", "discriminator"):
        weights = state.get(part) or {}
        broken = [
            name
            for name, value in weights.items()
            if isinstance(value, torch.Tensor) and not value.isfinite().all()
        ]
        if broken:
            raise DataError(
                f"{path} holds NaN or infinite {part} weights (e.g. {broken[0]}): the run "
                "diverged; start again from an earlier checkpoint"
            )


def _widens(trained: float, run: float) -> bool:
    """Whether a network of width ``run`` is a whole number (2 or more) of ``trained``'s."""
    ratio = run / trained
    return ratio > 1.5 and abs(ratio - round(ratio)) < 1e-9


def start_from(generator: nn.Module, config: TrainConfig) -> None:
    """Copy the weights ``config.init_from`` names into ``generator`` (fine-tuning).

    A PF-Net-family checkpoint trained at another missing ratio starts a run at this one:
    every weight is copied and the detail head's last layer resized
    (:func:`~pfnet.models.pfnet.resized_detail_head`). One of a narrower width that goes into
    the run's a whole number of times (0.25 into 0.5 or 1.0) starts a wider network that
    computes the same function (:func:`~pfnet.models.widen.widened_state`).

    Raises:
        ConfigError: The checkpoint is another network (model, width, cloud size, or a
            missing ratio a model without a point pyramid decoder cannot change).
    """
    from pfnet.inference.checkpoint import load_checkpoint
    from pfnet.models import build_model
    from pfnet.models.pfnet import resized_detail_head
    from pfnet.models.widen import LATENT_READER, widened_state

    source, trained = load_checkpoint(config.init_from)
    # a model that grows from another (pfnet-mirror from pfnet-vanilla) takes its weights
    grows = trained.model in getattr(generator, "grows_from", ())
    keys = (() if grows else ("model",)) + ("width", "n_points", "missing_ratio")
    head = "decoder.detail_conv.4.bias"  # the one layer of a point pyramid decoder sized by M
    if (
        trained.missing_ratio != config.missing_ratio
        and head in source.state_dict()
        and head in generator.state_dict()
    ):  # the same network at another missing ratio: start its detail head from the trained one
        trained = replace(trained, missing_ratio=config.missing_ratio)
        resized = build_model(trained)
        resized.load_state_dict(resized_detail_head(source.state_dict(), trained.n_missing))
        source = resized
    if _widens(trained.width, config.width) and LATENT_READER in source.state_dict():
        # a narrower network of the PF-Net family: the same function at the run's width
        trained = replace(trained, width=config.width)
        wide = build_model(trained)
        wide.load_state_dict(widened_state(source.state_dict(), wide, seed=config.seed))
        source = wide
    differ = [
        f"{k} {getattr(trained, k)!r} (run: {getattr(config, k)!r})"
        for k in keys
        if getattr(trained, k) != getattr(config, k)
    ]
    if differ:
        raise ConfigError(f"init_from {config.init_from} is another network: {', '.join(differ)}")
    if grows:
        generator.grow_from(source)
    else:
        generator.load_state_dict(source.state_dict())
