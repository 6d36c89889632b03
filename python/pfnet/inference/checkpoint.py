"""Training checkpoints: plain dicts of tensors and builtins (``torch.load(weights_only=True)``).

A checkpoint holds the configuration it was trained with, so ``load_checkpoint`` rebuilds the
model with nothing else. Keys: ``format``, ``version``, ``config`` (``TrainConfig.to_dict()``,
of which loading reads the :class:`~pfnet.models.ModelConfig` keys),
``model`` (generator state dict), ``discriminator`` (or ``None``), ``optimizer_g``,
``optimizer_d``, ``scheduler_g``, ``scheduler_d``, ``epoch`` (epochs completed),
``batches_done`` (batches of the current epoch already trained, for a mid-epoch resume),
``epoch_sums`` (running loss sums of that epoch), ``best_metric``, ``history`` (per-epoch log
rows), ``rng`` (torch CPU / CUDA generator states) and ``world_size``.

:func:`write_shipped` turns one into a shipped model file (:mod:`pfnet.inference.shipped`).
"""

from __future__ import annotations

import json
import os
import warnings
import zipfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from pfnet.errors import ConfigError, DataError
from pfnet.io.files import atomic_path
from pfnet.models.config import ModelConfig

if TYPE_CHECKING:
    from pfnet.models import CompletionModel

FORMAT = "pfnet-checkpoint"
VERSION = 1


def save_checkpoint(path: str | os.PathLike[str], state: dict[str, Any]) -> None:
    """Write ``state`` atomically (temporary file in the same folder, then rename)."""
    state = {"format": FORMAT, "version": VERSION, **state}
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def read_checkpoint(path: str | os.PathLike[str], device: str | torch.device = "cpu") -> dict:
    """Load a checkpoint dict with ``weights_only=True`` and check its format.

    Raises:
        DataError: Missing, unreadable or foreign file (naming the path).
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"checkpoint {path} does not exist")
    _check_stored(path)
    try:
        with warnings.catch_warnings():
            # torch warns of a foreign file's pickle protocol before refusing it: the refusal
            # is the one line the user gets
            warnings.filterwarnings("ignore", message="Detected pickle protocol")
            state = torch.load(path, map_location=device, weights_only=True)
    except Exception as err:  # torch raises many types for corrupt or unsafe files
        raise DataError(_unreadable(path, err)) from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise DataError(f"{path} is not a pfnet checkpoint")
    if state.get("version") != VERSION:
        raise DataError(
            f"checkpoint {path} has format version {state.get('version')}; "
            f"this pfnet reads version {VERSION}"
        )
    for key, kind in (("config", dict), ("model", dict)):
        if not isinstance(state.get(key), kind):
            raise DataError(f"checkpoint {path} has no {key!r} table: it is damaged or foreign")
    return state


def _unreadable(path: Path, err: Exception) -> str:
    """One line for a file ``torch.load(weights_only=True)`` refused.

    PyTorch's own text for a weights-only refusal advises re-running with
    ``weights_only=False``, which executes the file's code: it is never relayed.
    """
    if path.suffix.lower() == ".onnx":
        return (
            f"checkpoint {path} cannot be read: it is an ONNX model; "
            "a pfnet checkpoint (.pt) is needed"
        )
    first = (str(err).strip().splitlines() or [type(err).__name__])[0]
    if "weights" in first.lower() or "unpickl" in first.lower() or "pickle" in first.lower():
        detail = "pfnet loads only tensors and builtins and never unpickles code"
    else:
        detail = first[:200]
    return (
        f"checkpoint {path} cannot be read: not a pfnet checkpoint, "
        f"or not one that can be read safely ({detail})"
    )


def _check_stored(path: Path) -> None:
    """Refuse compressed members before ``torch.load`` unpacks them all.

    ``torch.save`` stores its archive uncompressed, so what loading unpacks is bounded by
    the file's size; a forged 5.6 MB checkpoint with a deflated 1.2 GB tensor took 1.7 GB.
    """
    try:
        with zipfile.ZipFile(path) as archive:
            packed = [
                i.filename for i in archive.infolist() if i.compress_type != zipfile.ZIP_STORED
            ]
    except (zipfile.BadZipFile, OSError, ValueError):
        return  # not a zip: torch.load names what is wrong
    if packed:
        raise DataError(
            f"checkpoint {path} has compressed members ({packed[0][:80]}, ...), which "
            "torch.save never writes: it is forged or damaged"
        )


def check_weights(path: Path, config: ModelConfig, weights: dict[str, Any]) -> None:
    """Check the stored weights against the model ``config`` describes, before building it.

    The model is built on PyTorch's ``meta`` device (shapes only, no memory), so a forged
    config describing a billion-parameter network costs nothing before it is refused.

    Raises:
        DataError: Missing, unexpected or mis-shaped tensors (the first few named).
    """
    from pfnet.models import build_model

    with torch.device("meta"):
        expected = {k: tuple(v.shape) for k, v in build_model(config).state_dict().items()}

    def plain(value: Any) -> bool:
        return (
            isinstance(value, torch.Tensor) and value.layout == torch.strided and not value.is_meta
        )

    problems = [f"{k} is not a plain tensor" for k, v in weights.items() if not plain(v)]
    stored = {k: tuple(v.shape) for k, v in weights.items() if plain(v)}
    problems += [f"missing {k}" for k in expected if k not in stored]
    problems += [f"unexpected {k}" for k in stored if k not in expected]
    problems += [
        f"{k} is {stored[k]}, expected {shape}"
        for k, shape in expected.items()
        if k in stored and stored[k] != shape
    ]
    if problems:
        more = f" and {len(problems) - 3} more" if len(problems) > 3 else ""
        raise DataError(
            f"checkpoint {path} does not match the model its config describes: "
            f"{'; '.join(problems[:3])}{more}"
        )


def inference_weights(state: dict[str, Any]) -> Any:
    """The generator weights a checkpoint's state offers for inference.

    The weight average of a run trained with ``ema`` (its ``last.pt`` holds the live weights
    too, for ``--resume``; its ``best.pt`` holds only the average, as ``model``), else
    ``model``.
    """
    average = state.get("average")
    if isinstance(average, dict) and "model" in average:
        return average["model"]
    return state["model"]


def load_checkpoint(
    path: str | os.PathLike[str] | None, device: str | torch.device = "cpu"
) -> tuple[CompletionModel, ModelConfig]:
    """Rebuild a trained generator from a checkpoint or a shipped model.

    Args:
        path: A ``last.pt`` or ``best.pt`` written by ``pfnet train``, a model file
            (``.safetensors``, :mod:`pfnet.inference.shipped`), or the name of a shipped model;
            ``None`` for the default shipped model. A run trained with ``ema`` gives its
            weight average from either checkpoint (:func:`inference_weights`).
        device: Where to put the model.

    Returns:
        ``(model, config)``: the generator (float32) in eval mode on ``device`` and its
        :class:`~pfnet.models.ModelConfig` (``model``, ``n_points``, ``n_missing``,
        ``missing_ratio``, ``width``); the training settings stay in the file.

    Raises:
        ConfigError: ``path`` names neither a file nor a shipped model.
        DataError: The file is unreadable or not a pfnet checkpoint or model file.
    """
    from pfnet.inference.shipped import SUFFIX, load_weights, read_metadata, resolve_checkpoint
    from pfnet.models import build_model

    path = resolve_checkpoint(path)
    if path.name.endswith(SUFFIX):
        config_dict, _ = read_metadata(path)
        weights = load_weights(path, device="cpu")
    else:
        state = read_checkpoint(path, device)
        config_dict, weights = state["config"], inference_weights(state)
    config = ModelConfig.from_dict(config_dict, source=f"checkpoint {path}", extra="ignore")
    try:
        check_weights(path, config, weights)
    except ConfigError as err:  # a config that builds no network ("n_points is not set")
        raise DataError(f"checkpoint {path}: {err}") from None
    model = build_model(config)
    try:
        model.load_state_dict(weights)  # copies float16 model files into float32 parameters
    except (RuntimeError, TypeError, ValueError) as err:  # what check_weights cannot foresee
        raise DataError(f"checkpoint {path} cannot be loaded: {str(err)[:200]}") from None
    broken = [name for name, value in model.state_dict().items() if not value.isfinite().all()]
    if broken:  # a diverged run's weights: every completion would be NaN
        raise DataError(
            f"checkpoint {path} holds NaN or infinite weights ({len(broken)} tensors, e.g. "
            f"{broken[0]}): the run diverged; use an earlier checkpoint"
        )
    return model.to(device).eval(), config


def write_shipped(
    checkpoint: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    card: dict[str, Any] | None = None,
    frame: str | None = None,
) -> Path:
    """Write a training checkpoint's generator as a model file (float tensors as float16).

    Args:
        checkpoint: ``best.pt`` or ``last.pt`` of ``pfnet train``, or a model file (its weights
            and config are kept and its card replaced: how a model trained elsewhere, e.g. on a
            GPU machine that returns only small files, gets the card measured here).
        out: The ``.safetensors`` file to write (atomically).
        card: The model card to store (data, recipe, metrics), JSON-serialisable.
        frame: ``heading`` to ship a run of the ``scan`` frame trained on partials in the
            data set's own heading (``--crop turned``, no ``--augment-rotate``) as a model of
            the ``heading`` frame: its training inputs were the heading frame's, and
            ``complete`` then turns each scan back by the heading the reader reads. No other
            change of frame is allowed (the network would see inputs it never trained on).

    Raises:
        ConfigError: Another change of frame, or a run whose partials were turned.
    """
    import torch
    from safetensors.torch import save_file

    from pfnet.inference import shipped
    from pfnet.inference.shipped import SUFFIX, load_weights, read_metadata

    out = Path(out)
    if not out.name.endswith(SUFFIX):
        raise ConfigError(f"a model file must end in {SUFFIX}, got {out}")
    if Path(checkpoint).name.endswith(SUFFIX):
        config, _ = read_metadata(checkpoint)
        state = {"config": config, "model": load_weights(checkpoint)}
    else:
        state = read_checkpoint(checkpoint)
    if frame is not None and frame != state["config"].get("frame", "shape"):
        state = {**state, "config": _reframed(state["config"], frame, checkpoint)}
    tensors = {
        key: (value.half() if value.is_floating_point() else value).contiguous()
        for key, value in inference_weights(state).items()
        if isinstance(value, torch.Tensor)
    }
    metadata = {
        "format": shipped.FORMAT,
        "version": shipped.VERSION,
        "config": json.dumps(state["config"]),
        "card": json.dumps(card or {}),
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        save_file(tensors, str(tmp), metadata=metadata)
        # safetensors creates its file readable by its owner only; give it the permissions
        # that the umask gives every other file pfnet writes
        umask = os.umask(0)
        os.umask(umask)
        tmp.chmod(0o666 & ~umask)
    return out


def _reframed(config: dict[str, Any], frame: str, source: Any) -> dict[str, Any]:
    """A run's config shipped in the ``heading`` frame (see :func:`write_shipped`)."""
    was = config.get("frame", "shape")
    if (was, frame) != ("scan", "heading"):
        raise ConfigError(
            f"{source}: a model of the {was} frame cannot be shipped as {frame} (only a scan "
            "run trained in the data set's heading ships as heading)"
        )
    if config.get("augment_rotate") or config.get("crop", "viewpoint") != "turned":
        raise ConfigError(
            f"{source}: only a run trained with --crop turned and no --augment-rotate (its "
            "partials in the data set's heading) ships in the heading frame"
        )
    return {**config, "frame": frame}
