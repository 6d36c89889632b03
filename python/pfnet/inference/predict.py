"""Running a trained model over a data set split with the deterministic test protocol, and the
network's input every path shares (:func:`input_frame`, :func:`network_input`).

``pfnet predict`` is the command around :func:`predict_split`; ``complete`` uses
:func:`predict_missing`. Output of :func:`predict_split`, ready for ``pfnet evaluate``::

    PRED/<category>/<name>.npy    float32 (M, 3): the predicted missing region
    PRED/predictions.json         checkpoint, data, split, protocol, model, files written

The folder and its record: :mod:`pfnet.evaluation.prediction_folder`,
:mod:`pfnet.evaluation.prediction_record`;
the field's benchmarks: :mod:`pfnet.inference.benchmarks`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from pfnet.data.sampling import Normalisation, unit_ball
from pfnet.errors import ConfigError, DataError
from pfnet.evaluation.prediction_folder import (
    check_prediction_folder,
    open_prediction_folder,
    write_record,
)
from pfnet.evaluation.prediction_record import run_files
from pfnet.inference.runtimes import check_detail


def normalisation(points: np.ndarray, source: str = "input") -> Normalisation:
    """Centre at the centroid and scale by the max radius (the scan frame), in float64.

    Raises:
        DataError: If all points coincide (no scale to normalise by).
    """
    transform = unit_ball(points)
    if transform is None:
        raise DataError(f"{source}: all {len(points)} points coincide; nothing to complete")
    return transform


def input_frame(points: np.ndarray, frame: str, source: str = "input") -> Any:
    """The frame a model of ``frame`` sees a partial cloud in, as a
    :class:`pfnet.data.scan_frame.ScanFrame` (``apply`` / ``invert``).

    Every path that normalises an input by itself (``complete``, ``predict`` of a scan-frame
    model, the PCN and KITTI protocols) goes through here, so that an ``aligned`` model is
    turned to the partial's main horizontal axis wherever it runs, and a ``heading`` model
    turned back by the heading :mod:`pfnet.data.heading`'s shipped reader reads.

    Raises:
        DataError: If all points coincide (no scale to normalise by).
    """
    from pfnet.data.scan_frame import frame_of, scan_frame

    normalisation(points, source)
    if frame == "heading":  # turned back by the heading the shipped reader reads
        from pfnet.data.heading import load_reader

        (heading,) = load_reader().headings([scan_frame(points).apply(points)])
        return scan_frame(points, heading=heading)
    return frame_of(points, frame)


def network_input(points: np.ndarray, n_input: int) -> np.ndarray:
    """Resample a normalised ``(N, 3)`` cloud to exactly ``n_input`` points.

    More points: iterative farthest point sampling from point 0. Fewer: cyclic repetition.

    Returns:
        float32 ``(n_input, 3)``.
    """
    from pfnet.data.sampling import fixed_size

    return fixed_size(points, n_input)


def predict_missing(
    model: Any, partial: np.ndarray, batch_size: int, device: str, *, source: Any = "in use"
) -> np.ndarray:
    """Run ``model`` over ``partial`` clouds in batches, checking each batch's output.

    Args:
        model: A completion model in eval mode (``forward(partial) -> Completion``), or an
            :class:`pfnet.inference.runtimes.OnnxGenerator` (which runs without torch).
        partial: float32 ``(S, n, 3)`` partial clouds.
        batch_size: Clouds per forward pass.
        device: Torch device the model lives on.
        source: The checkpoint the PyTorch model came from, named in errors (an ONNX model
            names its own file).

    Returns:
        float32 ``(S, M, 3)`` predicted missing regions.

    Raises:
        DataError: The model's output is not ``(batch, M, 3)`` finite points
            (:func:`~pfnet.inference.runtimes.check_detail`), or an ONNX model fails to run.
    """
    from pfnet.inference.runtimes import OnnxGenerator

    if isinstance(model, OnnxGenerator):
        return model.predict_missing(partial, batch_size)
    import torch
    from tqdm import tqdm

    if batch_size < 1:
        raise ConfigError(f"batch size must be at least 1, got {batch_size}")
    outputs = []
    starts = range(0, len(partial), batch_size)
    with torch.inference_mode():
        for start in tqdm(starts, desc="predict", unit="batch", disable=None, leave=False):
            batch = torch.from_numpy(np.ascontiguousarray(partial[start : start + batch_size]))
            completion = model(batch.to(device=device, dtype=torch.float32))
            detail = completion.detail.float().cpu().numpy()
            outputs.append(check_detail(detail, len(batch), model.n_missing, source))
    return np.concatenate(outputs).astype(np.float32, copy=False)


def predict_split(
    checkpoint: str | os.PathLike[str] | None,
    data_dir: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
    split: str = "test",
    missing_ratio: float | None = None,
    batch_size: int = 32,
    device: str = "auto",
    runtime: str = "auto",
    overwrite: bool = False,
) -> dict:
    """Predict every sample of ``split`` and write ``out_dir`` (see the module docstring).

    Args:
        checkpoint: A checkpoint written by ``pfnet train``, a model file or a shipped
            model's name; ``None`` for the default shipped model.
        data_dir: A prepared data set.
        out_dir: Prediction folder to create or fill (existing files are replaced); one
            holding another run's predictions is refused (:func:`check_prediction_folder`).
        split: ``train``, ``val`` or ``test``.
        missing_ratio: Ratio of the test crop; default: the checkpoint's training ratio.
        batch_size: Clouds per forward pass.
        device: ``auto``, ``cpu``, ``cuda`` or ``cuda:N``.
        runtime: ``auto``, ``torch`` or ``onnx`` (:func:`pfnet.inference.runtimes.load_generator`).
        overwrite: Replace another run's predictions in ``out_dir``.

    Returns:
        The ``predictions.json`` document.

    Raises:
        ConfigError: Bad device, batch size or ratio.
        DataError: Unreadable checkpoint or data set, clouds of another size than the model's,
            or a model output refused by :func:`~pfnet.inference.runtimes.check_detail`.
    """
    from pfnet.data import load_split, test_protocol_crop
    from pfnet.inference.runtimes import load_generator
    from pfnet.inference.shipped import describe, resolve_checkpoint
    from pfnet.io.clouds import save_npy
    from pfnet.io.files import refuse_overlap

    checkpoint = resolve_checkpoint(checkpoint)
    refuse_overlap(out_dir, [data_dir, checkpoint], flag="prediction folder")
    if Path(out_dir).exists() and not Path(out_dir).is_dir():
        raise ConfigError(
            f"prediction folder {out_dir} is a file; name a folder for the predictions"
        )
    replaced = check_prediction_folder(Path(out_dir), data_dir, split, "test", overwrite)
    loaded = load_generator(checkpoint, runtime=runtime, device=device)
    model, config, device = loaded.model, loaded.config, loaded.device
    trained_ratio = config.missing_ratio
    ratio = float(trained_ratio if missing_ratio is None else missing_ratio)
    if not 0.0 < ratio < 1.0:
        raise ConfigError(f"missing ratio must be in (0, 1), got {ratio}")
    clouds = load_split(data_dir, split)
    if len(clouds) == 0:
        raise DataError(f"split {split!r} of {data_dir} has no samples")
    points = np.asarray(clouds.points, dtype=np.float32)
    # The protocol's scores compare a region of the model's size with the true one: clouds
    # of another size would be scored without meaning (or, below 4 points, not run at all).
    # `complete` resamples a scan to the model's input instead; a benchmark must not.
    if points.shape[1] != config.n_points:
        raise DataError(
            f"split {split!r} of {data_dir} has clouds of {points.shape[1]} points, but model "
            f"{checkpoint} was trained on clouds of {config.n_points}; predict on a data set "
            f"prepared with {config.n_points} points per cloud"
        )
    config.replace(missing_ratio=ratio)  # ConfigError unless 1 to N - 4 points are removed
    partial, removed = test_protocol_crop(points, ratio)
    frame = getattr(config, "frame", "shape")
    if frame == "shape":  # the paper's protocol: the partial in the complete shape's frame
        detail = predict_missing(
            model, np.asarray(partial, dtype=np.float32), batch_size, device, source=checkpoint
        )
    else:  # a scan-frame model sees each partial in its own frame, as `complete` shows it
        frames = [input_frame(p, frame, f"sample {i}") for i, p in enumerate(partial)]
        batch = np.stack([f.apply(p) for f, p in zip(frames, partial, strict=True)])
        detail = predict_missing(model, batch, batch_size, device, source=checkpoint)
        detail = np.stack([f.invert(d) for f, d in zip(frames, detail, strict=True)])
        detail = detail.astype(np.float32)

    out = Path(out_dir)
    files = run_files(clouds.category, clouds.name)
    open_prediction_folder(
        out,
        files,
        split,
        {"name": "test", "missing_ratio": ratio},
        data_dir=data_dir,
        replaced=replaced,
    )
    for cat, name, cloud in zip(clouds.category, clouds.name, detail, strict=True):
        save_npy(out / str(cat) / f"{name}.npy", cloud)
    return write_record(
        out,
        describe(checkpoint),
        data_dir,
        split,
        files,
        loaded.runtime,
        device,
        protocol={
            "name": "test",
            "missing_ratio": ratio,
            "n_points": int(points.shape[1]),
            "n_missing": int(removed.shape[1]),
            "viewpoint": "VIEWPOINTS[i % 5] for sample i in split order",
            "input_frame": frame,
        },
        model={
            "name": config.model,
            "n_points": config.n_points,
            "missing_ratio": trained_ratio,
            "n_predicted": int(detail.shape[1]),
        },
        n_samples=len(clouds),
    )
