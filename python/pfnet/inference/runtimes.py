"""Where a generator runs: PyTorch, or ONNX Runtime without PyTorch.

``pfnet complete`` and ``pfnet predict`` take ``--runtime auto|torch|onnx``:

* ``torch`` loads a checkpoint, model file or shipped model with
  :func:`pfnet.inference.checkpoint.load_checkpoint` (needs the ``[train]`` extra).
* ``onnx`` runs an ONNX file written by ``pfnet export`` (:mod:`pfnet.inference.onnx_export`)
  on ONNX Runtime (the ``[infer]`` extra, no torch): a ``.onnx`` path, or a model file with
  its ONNX export beside it (``NAME.onnx`` next to ``NAME.safetensors``, as the shipped
  models have).
* ``auto`` (the default): an ``.onnx`` path runs on ONNX Runtime; anything else on PyTorch
  when it is installed, else on ONNX Runtime.

Both give a model with the same inference contract (``n_points``, ``n_missing``, and
:func:`pfnet.inference.predict.predict_missing` accepts either); their completions agree within
:data:`pfnet.inference.onnx_export.TOLERANCE`. Nothing here imports torch unless it is chosen.
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pfnet.errors import ConfigError, DataError, MissingDependency

RUNTIMES = ("auto", "torch", "onnx")
RUNTIME_HELP = (
    "auto: PyTorch if installed, else ONNX Runtime (an .onnx --checkpoint always runs on ONNX "
    "Runtime); torch; onnx (default: auto)"
)
# The hint names the package itself: it works however pfnet was installed (from PyPI as
# pfnet-completion, from a clone); "pip install 'pfnet[...]'" would fetch an unrelated
# project that holds the name pfnet on PyPI.
INFER_EXTRA = "pip install onnxruntime (the [infer] extra of pfnet-completion)"
ONNX_SUFFIX = ".onnx"

# A prediction is in the frame of its partial cloud normalised to the unit ball, where the true
# missing region lies within radius 1 and a working model's points stay within a few radii.
# A point a thousand radii out is no completion but a broken or forged model (weights that
# overflow, a graph that outputs 1e30), and mapped back it could leave float32.
MAX_PREDICTED_RADIUS = 1e3


def has_module(name: str) -> bool:
    """Whether ``name`` is an installed module (without importing it). A bare folder of that
    name in the working directory (a namespace package, e.g. an output folder ``torch/``) is
    not: it would be imported instead of the real one and have none of its attributes."""
    spec = importlib.util.find_spec(name)
    return spec is not None and spec.origin is not None


class OnnxGenerator:
    """A generator exported by ``pfnet export``, run by ONNX Runtime.

    Args:
        path: The ``.onnx`` file.
        device: ``cpu`` or ``cuda[:N]`` (the latter needs ``onnxruntime-gpu``).

    Attributes:
        n_points, n_missing: As the PyTorch generator's.
        config: The training configuration stored in the file (a dict).
        metadata: All of the file's metadata (see :mod:`pfnet.inference.onnx_export`).
        device: Where it runs: ``cpu`` or ``cuda[:N]``.
        path: The file.

    Raises:
        MissingDependency: ONNX Runtime is not installed.
        DataError: The file is not a readable pfnet ONNX export.
    """

    def __init__(self, path: str | os.PathLike[str], device: str = "cpu") -> None:
        from pfnet.inference.onnx_graph import FORMAT, VERSION, check_graph

        ort = import_onnxruntime("the ONNX runtime")
        self.path = Path(path)
        options = ort.SessionOptions()
        # ORT's own log is not the user's business: its errors come back as exceptions too
        options.log_severity_level = 4
        # a model file from elsewhere: only a graph a pfnet export could be (no loops, no
        # unbounded allocations) is given to ORT
        check_graph(self.path)
        try:
            self.session = ort.InferenceSession(
                str(self.path), options, providers=_providers(ort, device)
            )
        except Exception as err:  # ORT raises its own types for missing or corrupt files
            first = (str(err).strip().splitlines() or [type(err).__name__])[0][:200]
            raise DataError(f"ONNX model {self.path} cannot be read: {first}") from None
        meta = self.session.get_modelmeta().custom_metadata_map
        if meta.get("format") != FORMAT:
            raise DataError(f"{self.path} is not a pfnet ONNX model (no {FORMAT!r} metadata)")
        if meta.get("version") != VERSION:
            raise DataError(
                f"ONNX model {self.path} has format version {meta.get('version')}; "
                f"this pfnet reads version {VERSION}"
            )
        try:
            self.n_points = int(meta["n_points"])
            self.n_missing = int(meta["n_missing"])
            self.config = json.loads(meta["config"])
        except (KeyError, ValueError, RecursionError) as err:
            raise DataError(f"ONNX model {self.path} has broken metadata: {err}") from None
        if not isinstance(self.config, dict) or not 0 < self.n_missing < self.n_points:
            raise DataError(f"ONNX model {self.path} has broken metadata")
        self.metadata = dict(meta)
        self.inputs = [i.name for i in self.session.get_inputs()]
        providers = self.session.get_providers()
        self.device = device if "CUDAExecutionProvider" in providers else "cpu"
        self.device = "cuda" if self.device == "auto" else self.device
        self._check_signature()

    def _check_signature(self) -> None:
        """Refuse a graph whose declared inputs or output are not a pfnet export's: ``partial``
        float ``(batch, points, 3)`` [+ ``scale_indices`` int64 ``(batch, half)``] ->
        ``detail`` float ``(batch, n_missing, 3)``. (The output is checked again after each
        run: declared shapes may be symbolic.)"""
        # a name stands for a free axis, where a fixed size (a batch of 1) is refused too
        expected = {
            "partial": ("tensor(float)", ("batch", "points", 3)),
            "scale_indices": ("tensor(int64)", ("batch", "half")),
            "detail": ("tensor(float)", ("batch", self.n_missing, 3)),
        }
        outputs = [o.name for o in self.session.get_outputs()]
        if self.inputs not in (["partial"], ["partial", "scale_indices"]) or outputs != ["detail"]:
            raise DataError(
                f"ONNX model {self.path} has inputs {self.inputs[:4]} and outputs "
                f"{outputs[:4]}, not a pfnet export's (partial[, scale_indices]) -> detail"
            )
        for arg in [*self.session.get_inputs(), *self.session.get_outputs()]:
            kind, dims = expected[arg.name]
            shape = arg.shape  # ints, and names or None for free axes; None if undeclared
            fits = shape is None or (
                len(shape) == len(dims)
                and all(
                    not isinstance(got, int) if isinstance(want, str) else got == want
                    for got, want in zip(shape, dims, strict=True)
                )
            )
            if arg.type != kind or not fits:
                raise DataError(
                    f"ONNX model {self.path}: {arg.name} is declared {arg.type} "
                    f"{list(shape or [])[:6]}, but pfnet expects {kind} "
                    f"({', '.join(map(str, dims))})"
                )

    def predict(self, partial: np.ndarray) -> np.ndarray:
        """float32 ``(B, n, 3)`` normalised partial clouds -> float32 ``(B, M, 3)``.

        Raises:
            DataError: The model fails to run or its output is not ``(B, M, 3)`` finite points
                (:func:`check_detail`).
        """
        from pfnet.geometry import farthest_point_sample

        partial = np.ascontiguousarray(partial, dtype=np.float32)
        feeds = {"partial": partial}
        if "scale_indices" in self.inputs:  # the IFPS prefix, as the PyTorch encoder takes
            index = farthest_point_sample(partial, partial.shape[1] // 2)
            feeds["scale_indices"] = np.asarray(index, dtype=np.int64)
        try:
            (detail,) = self.session.run(["detail"], feeds)
        except Exception as err:  # ORT's own types: a failed allocation, a bad node
            first = (str(err).strip().splitlines() or [type(err).__name__])[0][:200]
            raise DataError(f"ONNX model {self.path} failed to run: {first}") from None
        return check_detail(detail, len(partial), self.n_missing, self.path)

    def predict_missing(self, partial: np.ndarray, batch_size: int) -> np.ndarray:
        """:func:`pfnet.inference.predict.predict_missing` on ONNX Runtime: ``(S, n, 3)`` in
        batches."""
        from tqdm import tqdm

        if batch_size < 1:
            raise ConfigError(f"batch size must be at least 1, got {batch_size}")
        starts = range(0, len(partial), batch_size)
        outputs = [
            self.predict(partial[start : start + batch_size])
            for start in tqdm(starts, desc="predict", unit="batch", disable=None, leave=False)
        ]
        return np.concatenate(outputs).astype(np.float32, copy=False)


def import_onnxruntime(needed_by: str) -> Any:
    """``onnxruntime``, or a one-line :class:`MissingDependency` naming the extra."""
    if not has_module("onnxruntime"):
        raise MissingDependency(f"{needed_by} needs ONNX Runtime, not installed: {INFER_EXTRA}")
    import onnxruntime

    return onnxruntime


def _providers(ort: Any, device: str) -> list:
    """ONNX Runtime execution providers for ``device`` (auto: CUDA when ORT has it)."""
    cuda = "CUDAExecutionProvider" in ort.get_available_providers()
    if device in ("auto", "cpu"):
        return (["CUDAExecutionProvider"] if cuda and device == "auto" else []) + [
            "CPUExecutionProvider"
        ]
    match = re.fullmatch(r"cuda(?::(\d+))?", device)
    if match is None:
        raise ConfigError(f"device must be auto, cpu, cuda or cuda:N, got {device!r}")
    if not cuda:
        raise ConfigError(
            f"device {device}: this ONNX Runtime has no CUDA (install onnxruntime-gpu, or run "
            "on PyTorch, or on the CPU)"
        )
    return [("CUDAExecutionProvider", {"device_id": int(match.group(1) or 0)})]


@dataclass
class LoadedGenerator:
    """A generator ready for inference and where it came from.

    Attributes:
        model: The PyTorch generator (eval mode) or an :class:`OnnxGenerator`.
        config: Its network's :class:`~pfnet.models.ModelConfig`.
        device: Where it runs (``cpu``, ``cuda``, ``cuda:N``).
        runtime: ``torch`` or ``onnx``.
        source: The checkpoint, model file or ONNX file named by ``--checkpoint``.
    """

    model: Any
    config: Any
    device: str
    runtime: str
    source: Path


def load_generator(
    checkpoint: str | os.PathLike[str] | None, *, runtime: str = "auto", device: str = "auto"
) -> LoadedGenerator:
    """Load a generator for inference on the runtime ``runtime`` (see the module docstring).

    Args:
        checkpoint: A checkpoint, model file, ``.onnx`` file or shipped model's name; ``None``
            for the default shipped model.
        runtime: ``auto``, ``torch`` or ``onnx``.
        device: ``auto``, ``cpu``, ``cuda`` or ``cuda:N``.

    Raises:
        ConfigError: Unknown runtime or device, a checkpoint the runtime cannot run.
        MissingDependency: Neither PyTorch nor ONNX Runtime is installed for the choice.
        DataError: An unreadable file.
    """
    from pfnet.inference.shipped import resolve_checkpoint

    if runtime not in RUNTIMES:
        raise ConfigError(f"runtime must be one of {', '.join(RUNTIMES)}, got {runtime!r}")
    source = resolve_checkpoint(checkpoint)
    is_onnx = source.suffix.lower() == ONNX_SUFFIX
    if is_onnx and runtime == "torch":
        raise ConfigError(f"{source} is an ONNX model: it runs on ONNX Runtime, not PyTorch")
    if runtime == "torch" or (runtime == "auto" and not is_onnx and has_module("torch")):
        from pfnet.inference.checkpoint import load_checkpoint
        from pfnet.inference.devices import inference_device

        device = inference_device(device)
        model, config = load_checkpoint(source, device=device)
        return LoadedGenerator(model, config, device, "torch", source)
    if runtime == "auto" and not has_module("onnxruntime"):
        raise MissingDependency(
            f"completing needs ONNX Runtime (or PyTorch); neither is installed: {INFER_EXTRA}"
        )
    model = OnnxGenerator(source if is_onnx else onnx_export_of(source), device)
    if not is_onnx:
        from pfnet.inference.onnx_graph import file_sha256

        if model.metadata.get("source_sha256") != file_sha256(source):
            raise DataError(
                f"{model.path} was not exported from {source} (its weights differ); export it again"
            )
    from pfnet.models.config import ModelConfig

    config = ModelConfig.from_dict(model.config, source=f"ONNX model {model.path}", extra="ignore")
    recorded = (model.n_points, model.n_missing)
    if config.n_points is None or (config.n_points, config.n_missing) != recorded:
        raise DataError(
            f"ONNX model {model.path}: its metadata says {recorded[0]} points with "
            f"{recorded[1]} missing, its training configuration {config.n_points} points "
            f"with ratio {config.missing_ratio}"
        )
    return LoadedGenerator(model, config, model.device, "onnx", source)


def onnx_export_of(source: Path) -> Path:
    """The ONNX export beside a model file: ``NAME.onnx`` next to ``NAME.safetensors``.

    (The export records the SHA-256 of the file it came from, which
    :func:`load_generator` checks.)

    Raises:
        ConfigError: There is none (the message says how to make one).
    """
    candidate = source.with_suffix(ONNX_SUFFIX)
    if not candidate.is_file():
        torch_hint = "" if has_module("torch") else " where PyTorch is installed"
        raise ConfigError(
            f"{source} has no ONNX export to run without PyTorch; make one{torch_hint} with "
            f"`pfnet export --checkpoint {source} --out {candidate}`"
        )
    return candidate


def check_detail(detail: Any, batch: int, n_missing: int, source: Any) -> np.ndarray:
    """A model's output for ``batch`` clouds, checked: float32 ``(batch, n_missing, 3)``,
    finite, and within :data:`MAX_PREDICTED_RADIUS` of the unit ball's centre.

    Args:
        detail: What the forward pass returned (a numpy array, or anything a forged model gave).
        batch: Clouds in the forward pass.
        n_missing: M, the points the model is configured to predict.
        source: The checkpoint or model file, named in the message.

    Returns:
        ``detail`` as a float32 array.

    Raises:
        DataError: Any other output: the model or its weights are broken, nothing is written.
    """
    want = (batch, n_missing, 3)
    if not isinstance(detail, np.ndarray) or detail.dtype.kind != "f" or detail.shape != want:
        got = (
            f"{detail.dtype} {detail.shape}"
            if isinstance(detail, np.ndarray)
            else type(detail).__name__
        )
        raise DataError(
            f"model {source} predicted {got}, not float {want} (batch, missing points, xyz); "
            "it is not a working pfnet model"
        )
    if not np.isfinite(detail).all():
        raise DataError(
            f"model {source} predicted NaN or infinite coordinates; it is not a working model "
            "(do its weights overflow?)"
        )
    # max |coordinate| rather than the norm: the bound is loose and this cannot overflow
    furthest = float(np.abs(detail).max(initial=0.0))
    if furthest > MAX_PREDICTED_RADIUS:
        raise DataError(
            f"model {source} predicted a coordinate of {furthest:.3g} in the unit ball's frame "
            f"(at most {MAX_PREDICTED_RADIUS:g} expected); it is not a working model"
        )
    return detail.astype(np.float32, copy=False)  # after the bound: float64 1e300 would warn
