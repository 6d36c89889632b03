"""Exporting a trained generator to ONNX, so that completion runs without PyTorch.

The exported graph is the generator's ``forward`` in eval mode, returning the detail points:

    partial        float32 (batch, points, 3)        the normalised partial clouds
    scale_indices  int64   (batch, points // 2)      multi-resolution models only: the IFPS
                                                     prefix of :func:`multi_resolution_indices`
    detail         float32 (batch, M, 3)             the predicted missing region

The batch and point axes are dynamic. The coarser scales of the multi-resolution encoder are
IFPS samples computed by the Rust core outside the network (as the PyTorch path does), so
they enter as indices; the graph gathers them.

Exporter: ``torch.onnx.export(dynamo=True)`` (``torch.export`` + onnxscript). Measured on the
shipped model it gives 105 nodes where the TorchScript exporter gives 198 (its shape
arithmetic adds chains of ``Constant``/``Cast``/``Where`` nodes), and the TorchScript
exporter is deprecated since torch 2.9. Its cost is the export time (~20 s on 2 cores).

Storage: every float32 initialiser whose values are all exactly float16 numbers is stored
as float16 and cast back to float32 by a ``Cast`` node (ONNX Runtime folds the casts when
it loads the model). That loses nothing by construction; for a shipped model, whose weights
are float16, it halves the file. Weights that are not float16-exact (those the exporter
folded BatchNorm into, or a float32 training checkpoint's) stay float32.

Metadata (``metadata_props``, readable without the weights): ``format``, ``version``,
``pfnet_version``, ``model``, ``preset``, ``n_points``, ``n_missing``, ``width``,
``missing_ratio``, ``config`` (the training configuration as JSON), ``card`` (a shipped
model's card), ``source`` and ``source_sha256`` (the file exported, see
:func:`pfnet.inference.runtimes.load_generator`).
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from pfnet.errors import ConfigError, DataError
from pfnet.inference.onnx_graph import FORMAT, VERSION, file_sha256

TOLERANCE = 1e-4
"""Largest absolute difference, in normalised coordinates (the unit ball), accepted between
ONNX Runtime's and PyTorch's detail points; measured differences are ~1e-6."""


def example_input(n_input: int, batch: int = 2, seed: int = 0) -> np.ndarray:
    """float32 ``(batch, n_input, 3)`` clouds inside the unit ball, for tracing and checks."""
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(batch, n_input, 3))
    points /= np.linalg.norm(points, axis=2).max(axis=1)[:, None, None]
    return points.astype(np.float32)


def _generator_graph(model: Any, multi_resolution: bool, n_input: int) -> Any:
    """Export ``model`` with torch's dynamo exporter; returns the ``onnx.ModelProto``."""
    import torch
    from torch import nn

    from pfnet.models.layers import multi_resolution_indices

    class Detail(nn.Module):
        """The generator's detail points only: what completion uses."""

        def __init__(self) -> None:
            super().__init__()
            self.generator = model

        def forward(self, partial, scale_indices=None):
            return self.generator(partial, scale_indices).detail

    partial = torch.from_numpy(example_input(n_input))
    batch, points = torch.export.Dim("batch"), torch.export.Dim("points", min=4)
    args: tuple = (partial,)
    names = ["partial"]
    shapes: tuple = ({0: batch, 1: points},)
    if multi_resolution:
        args += (torch.from_numpy(multi_resolution_indices(partial)),)
        names.append("scale_indices")
        shapes += ({0: batch, 1: torch.export.Dim("half", min=2)},)
    # The exporter prints its progress, logs that torchvision is absent and warns about
    # axis names: none of it concerns the user.
    logger = logging.getLogger("torch.onnx")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
            warnings.simplefilter("ignore")
            program = torch.onnx.export(
                Detail().eval(),
                args,
                dynamo=True,
                input_names=names,
                output_names=["detail"],
                dynamic_shapes=shapes,
                verbose=False,
            )
    finally:
        logger.setLevel(level)
    return program.model_proto


def shrink_initializers(graph_model: Any) -> int:
    """Store float16-exact float32 initialisers as float16 + ``Cast``; returns how many."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    graph = graph_model.graph
    casts, kept, count = [], [], 0
    for init in graph.initializer:
        array = numpy_helper.to_array(init)
        if array.dtype == np.float32 and array.size > 16:
            half = array.astype(np.float16)
            if np.array_equal(half.astype(np.float32), array):
                stored = numpy_helper.from_array(half, f"{init.name}__fp16")
                kept.append(stored)
                casts.append(
                    helper.make_node(
                        "Cast", [stored.name], [init.name], to=TensorProto.FLOAT, name=stored.name
                    )
                )
                count += 1
                continue
        kept.append(init)
    del graph.initializer[:]
    graph.initializer.extend(kept)
    nodes = casts + list(graph.node)
    del graph.node[:]
    graph.node.extend(nodes)
    onnx.checker.check_model(graph_model)
    return count


def export_onnx(
    checkpoint: str | os.PathLike[str] | None,
    out: str | os.PathLike[str],
    *,
    check: bool = True,
) -> dict[str, Any]:
    """Export a checkpoint's or model file's generator to an ONNX file (see the module doc).

    Args:
        checkpoint: ``best.pt``/``last.pt``, a ``.safetensors`` model file or a shipped
            model's name; ``None`` for the default shipped model.
        out: The ``.onnx`` file to write (atomically).
        check: Run the file with ONNX Runtime (when installed) on example clouds and
            compare with PyTorch.

    Returns:
        What was written: ``path``, ``size_mb``, ``float16_tensors``, ``max_abs_diff``
        (``None`` without a check) and the metadata.

    Raises:
        ConfigError: ``out`` is not a ``.onnx`` path, or the checkpoint is not found.
        DataError: The model's own output is refused as ``complete`` and ``predict`` refuse
            it (:func:`pfnet.inference.runtimes.check_detail`: NaN, infinite or far-out points), or
            the exported graph disagrees with PyTorch beyond :data:`TOLERANCE`.
    """
    import onnx

    from pfnet import __version__
    from pfnet.inference.checkpoint import load_checkpoint, read_checkpoint
    from pfnet.inference.shipped import SUFFIX, describe, read_metadata, resolve_checkpoint
    from pfnet.io.files import atomic_path

    out = Path(out)
    if out.suffix.lower() != ".onnx":
        raise ConfigError(f"the ONNX file must be a .onnx path, got {out}")
    source = resolve_checkpoint(checkpoint)
    model, config = load_checkpoint(source, device="cpu")
    if source.name.endswith(SUFFIX):
        config_dict, card = read_metadata(source)
    else:  # the whole training configuration, not only the network's part of it
        config_dict, card = read_checkpoint(source)["config"], {}
    multi_resolution = model.multi_resolution
    n_input = int(model.n_points) - int(model.n_missing)
    # a model that complete and predict refuse is not exported either
    _torch_detail(model, example_input(n_input), source)
    graph_model = _generator_graph(model, multi_resolution, n_input)
    float16 = shrink_initializers(graph_model)
    metadata = {
        "format": FORMAT,
        "version": VERSION,
        "pfnet_version": __version__,
        "model": str(config.model),
        "preset": str(config_dict.get("preset")),
        "n_points": str(model.n_points),
        "n_missing": str(model.n_missing),
        "width": str(config.width),
        "missing_ratio": str(config.missing_ratio),
        "config": json.dumps(config_dict),
        "card": json.dumps(card),
        "source": describe(source),
        "source_sha256": file_sha256(source),
    }
    onnx.helper.set_model_props(graph_model, metadata)
    graph_model.doc_string = f"PF-Net generator {metadata['model']} exported by pfnet"
    max_diff = (
        _compare_with_torch(graph_model, model, multi_resolution, n_input, source)
        if check
        else None
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        onnx.save_model(graph_model, str(tmp))
    return {
        "path": out,
        "size_mb": out.stat().st_size / 1e6,
        "float16_tensors": float16,
        "max_abs_diff": max_diff,
        "metadata": metadata,
    }


def _torch_detail(model: Any, partial: np.ndarray, source: Path) -> np.ndarray:
    """PyTorch's detail points for ``partial``, checked as ``complete`` and ``predict`` check
    a model's output (:func:`pfnet.inference.runtimes.check_detail`: refused with a DataError)."""
    import torch

    from pfnet.inference.runtimes import check_detail
    from pfnet.models.layers import multi_resolution_indices

    index = multi_resolution_indices(partial) if model.multi_resolution else None
    with torch.inference_mode():
        index = None if index is None else torch.from_numpy(index)
        detail = model(torch.from_numpy(partial), index).detail.numpy()
    return check_detail(detail, len(partial), int(model.n_missing), source)


def _compare_with_torch(
    graph_model: Any, model: Any, multi_resolution: bool, n_input: int, source: Path
) -> float | None:
    """Max abs difference of ONNX Runtime vs PyTorch on example clouds (None without ORT)."""
    import importlib.util

    if importlib.util.find_spec("onnxruntime") is None:
        return None
    import onnxruntime as ort

    from pfnet.models.layers import multi_resolution_indices

    options = ort.SessionOptions()
    options.log_severity_level = 3
    session = ort.InferenceSession(
        graph_model.SerializeToString(), options, providers=["CPUExecutionProvider"]
    )
    worst = 0.0
    for batch, n in ((3, n_input), (1, max(4, n_input // 2 + 1))):
        partial = example_input(n, batch=batch, seed=n)
        feeds = {"partial": partial}
        if multi_resolution:
            feeds["scale_indices"] = multi_resolution_indices(partial)
        got = session.run(None, feeds)[0]
        want = _torch_detail(model, partial, source)
        difference = float(np.abs(got - want).max())
        if not difference <= TOLERANCE:  # NaN included
            raise DataError(
                f"ONNX Runtime's completion differs from PyTorch's by {difference:.3g} "
                f"(tolerance {TOLERANCE:g}); the file was not written"
            )
        worst = max(worst, difference)
    return worst
