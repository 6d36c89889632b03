"""Trained models shipped inside the package: completion with no training run and no download.

A shipped model is one ``safetensors`` file in ``pfnet/weights/``: the generator's weights
(floating-point tensors stored as float16, which halves the file and changes completions by
far less than the metrics resolve) and, in the file's metadata, the training configuration
and a model card (data, recipe, measured test metrics). Reading the metadata needs neither
torch nor the tensors, so ``pfnet models`` lists models instantly.

Wherever a command takes ``--checkpoint``, it accepts a checkpoint path (``best.pt`` /
``last.pt`` of ``pfnet train``, or a ``.safetensors`` file written by
:func:`pfnet.inference.checkpoint.write_shipped`)
or the name of a shipped model; with none, ``complete`` and ``predict`` use
:data:`DEFAULT_MODEL`.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pfnet.errors import ConfigError, DataError

FORMAT = "pfnet-shipped-model"
VERSION = "1"
WEIGHTS_DIR = Path(__file__).parent.parent / "weights"
SUFFIX = ".safetensors"
# The model `complete` and `predict` use when no --checkpoint is given.
# The best on the scan protocol (docs/scan-protocol.md): what `pfnet complete` gets.
DEFAULT_MODEL = "sh3d-mirror"

# The help of every command's --checkpoint: what resolve_checkpoint accepts.
CHECKPOINT_HELP = (
    "checkpoint (best.pt of pfnet train), model file or shipped model's name "
    "(default: the shipped default model; see pfnet models)"
)


@dataclass(frozen=True)
class ShippedModel:
    """One model file and what its metadata says about it."""

    name: str
    path: Path
    config: dict[str, Any]
    card: dict[str, Any]

    @property
    def size_mb(self) -> float:
        """The file's size in MB."""
        return self.path.stat().st_size / 1e6


def read_metadata(path: str | os.PathLike[str]) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(config, card)`` from a model file's header, without reading its tensors.

    Raises:
        DataError: Not a readable pfnet model file (naming the path).
    """
    from safetensors import safe_open

    path = Path(path)
    try:
        with safe_open(str(path), framework="numpy") as handle:
            metadata = handle.metadata() or {}
    except Exception as err:  # safetensors raises its own error types for bad headers
        raise DataError(f"model file {path} cannot be read: {err}") from None
    if metadata.get("format") != FORMAT:
        raise DataError(f"{path} is not a pfnet model file (no {FORMAT!r} metadata)")
    if metadata.get("version") != VERSION:
        raise DataError(
            f"model file {path} has format version {metadata.get('version')}; "
            f"this pfnet reads version {VERSION}"
        )
    try:
        config = json.loads(metadata["config"])
        card = json.loads(metadata.get("card", "{}"))
    except (KeyError, ValueError, RecursionError) as err:  # RecursionError: forged nesting
        raise DataError(f"model file {path} has a broken header: {err}") from None
    if not isinstance(config, dict) or not isinstance(card, dict):
        raise DataError(f"model file {path} has a broken header: config and card must be maps")
    return config, card


def shipped_models() -> list[ShippedModel]:
    """Every model shipped with this installation, by name."""
    models = []
    for path in sorted(WEIGHTS_DIR.glob(f"*{SUFFIX}")):
        config, card = read_metadata(path)
        models.append(ShippedModel(path.name[: -len(SUFFIX)], path, config, card))
    return models


def resolve_checkpoint(value: str | os.PathLike[str] | None) -> Path:
    """The file behind a ``--checkpoint`` value: an existing path, else a shipped model's name.

    ``None`` means the default shipped model; ``shipped:NAME`` only ever the shipped model.
    A bare name that is both a file here and a shipped model is refused (the file once
    replaced the model silently).

    Raises:
        ConfigError: Neither a file nor a shipped model's name.
    """
    if value is None:
        value = DEFAULT_MODEL
    name = str(value)
    if name.startswith("shipped:"):  # as outputs name it: only ever the shipped model
        name = name[len("shipped:") :]
        candidate = WEIGHTS_DIR / f"{name}{SUFFIX}"
        if os.sep not in name and "/" not in name and candidate.is_file():
            return candidate
        names = ", ".join(model.name for model in shipped_models()) or "none"
        raise ConfigError(f"no shipped model {name!r} (shipped: {names})")
    path = Path(value)
    candidate = WEIGHTS_DIR / f"{name}{SUFFIX}"
    shipped = os.sep not in name and "/" not in name and candidate.is_file()
    if path.is_file():
        if shipped:  # a file in the working folder would silently replace the shipped model
            raise ConfigError(
                f"checkpoint {name!r} is both a file in this folder and a shipped model; "
                f"name the file ./{name}, or the model shipped:{name}"
            )
        check_model_kind(path)
        return path
    if shipped:
        return candidate
    if path.exists():
        raise ConfigError(f"checkpoint {path} is not a file")
    names = ", ".join(model.name for model in shipped_models()) or "none in this installation"
    if path.suffix or len(path.parts) > 1:  # meant as a file
        raise ConfigError(f"checkpoint {path} does not exist")
    raise ConfigError(
        f"no checkpoint file {name!r} and no shipped model of that name (shipped: {names}; "
        f"list them with `pfnet models`)"
    )


# What each kind of model file is called, and the suffix that makes pfnet read it as such.
_KINDS = {
    "pytorch": ("a PyTorch checkpoint", ".pt"),
    "safetensors": ("a safetensors model file", SUFFIX),
    "onnx": ("an ONNX model", ".onnx"),
}


def model_file_kind(path: Path) -> str | None:
    """What the first bytes of ``path`` say it is: ``pytorch`` (a zip), ``safetensors`` (a
    length, then a JSON header), ``onnx`` (a protobuf starting with its IR version) or
    ``None`` when they say none of these for sure (an old pickled checkpoint, junk)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(16)
            size = os.fstat(fh.fileno()).st_size
    except OSError:
        return None
    if head[:4] == b"PK\x03\x04":
        return "pytorch"
    if len(head) > 8 and head[8:9] == b"{" and int.from_bytes(head[:8], "little") < size:
        return "safetensors"
    if (
        len(head) > 2
        and head[0] == 0x08
        and head[1] < 0x80
        and head[2] in b"\x12\x1a\x22\x28\x3a\x42"
    ):
        return "onnx"
    return None


def check_model_kind(path: Path) -> None:
    """Refuse a model file whose suffix says another kind than its bytes (an ONNX model named
    ``.pt`` was reported as an unreadable checkpoint, a ``.pt`` named ``.safetensors`` as a
    header error).

    Raises:
        ConfigError: Naming the file, what it is and the suffix to give it.
    """
    expected = {SUFFIX: "safetensors", ".onnx": "onnx"}.get(path.suffix.lower(), "pytorch")
    kind = model_file_kind(path)
    if kind is not None and kind != expected:
        what, suffix = _KINDS[kind]
        raise ConfigError(
            f"{path} is {what}, not {_KINDS[expected][0]} as its name says; rename it to "
            f"{path.with_suffix(suffix).name}"
        )


def describe(path: Path) -> str:
    """How outputs name the model: ``shipped:NAME`` or the file's absolute path."""
    if path.parent.resolve() == WEIGHTS_DIR.resolve() and path.name.endswith(SUFFIX):
        return f"shipped:{path.name[: -len(SUFFIX)]}"
    return str(path.resolve())


def load_weights(path: str | os.PathLike[str], device: str = "cpu") -> dict[str, Any]:
    """The tensors of a model file as torch tensors on ``device``."""
    from safetensors.torch import load_file

    try:
        return load_file(str(path), device=str(device))
    except Exception as err:  # corrupt or truncated file
        raise DataError(f"model file {path} cannot be read: {err}") from None
