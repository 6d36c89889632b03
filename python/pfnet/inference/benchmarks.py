"""The field's benchmarks predicted with a PF-Net model: whole completions of PCN's given
partial scans, of ShapeNet-55/34's crops from 8 viewpoints, and of KITTI's cars, for ``pfnet
evaluate --protocol`` (:mod:`pfnet.evaluation.benchmarks`). ``pfnet predict --protocol``
is the command around :func:`predict_benchmark`.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pfnet.errors import ConfigError, DataError
from pfnet.evaluation.prediction_folder import (
    check_prediction_folder,
    open_prediction_folder,
    write_record,
)
from pfnet.evaluation.prediction_record import run_files
from pfnet.evaluation.protocols import check_protocol_data, get_protocol
from pfnet.inference.predict import predict_missing

# Skipped shapes named in predictions.json.
MAX_SKIPPED_LISTED = 100


def predict_benchmark(
    checkpoint: str | os.PathLike[str] | None,
    data_dir: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    protocol: str,
    *,
    split: str = "test",
    missing_ratio: float | None = None,
    batch_size: int = 32,
    device: str = "auto",
    runtime: str = "auto",
    chunk: int = 256,
    overwrite: bool = False,
) -> dict:
    """Complete every input of a benchmark protocol (``pcn``, ``shapenet55``) with a PF-Net
    model and write the whole completions for ``pfnet evaluate --protocol``.

    * ``pcn``: the input is the shape's given partial scan; as ``pfnet complete`` does, it
      is normalised (centroid, max radius), resampled to the model's partial size (IFPS, or
      cyclic repetition), and the predicted missing region is mapped back. The completion
      is the scan followed by the prediction: ``PRED/<category>/<name>.npy``.
    * ``shapenet55``: the input is PoinTr's 2,048-point crop from each of the 8 viewpoints
      (:func:`pfnet.evaluation.protocols.shapenet_crop`), already in the data set's unit ball,
      reduced to the model's partial size by IFPS; the completion is the 2,048 input points followed
      by the prediction: ``PRED/<category>/<name>_view<v>.npy``.

    Returns:
        The ``predictions.json`` document.

    Raises:
        ConfigError: Bad protocol, ratio, device or batch size.
        DataError: Unreadable checkpoint or data set; a data set without partial scans
            (``pcn``); a prediction folder of another run without ``overwrite``
            (:func:`check_prediction_folder`); every partial scan degenerate.

    A partial scan whose points all coincide (nothing to normalise) is skipped: no file is
    written for it, its message is in the record's ``skipped`` (the first
    :data:`MAX_SKIPPED_LISTED`) and ``n_skipped``.
    """
    from pfnet.data import load_split
    from pfnet.evaluation.protocols import get_protocol, shapenet_crop
    from pfnet.inference.predict import input_frame, network_input
    from pfnet.inference.runtimes import load_generator
    from pfnet.inference.shipped import describe, resolve_checkpoint
    from pfnet.io.clouds import save_npy
    from pfnet.io.files import refuse_overlap

    chosen = get_protocol(protocol)
    if chosen.prediction != "complete":
        raise ConfigError(f"protocol {chosen.name!r} is predicted by predict_split")
    if chosen.name == "kitti":
        if missing_ratio is not None:
            raise ConfigError("the kitti protocol takes no missing ratio (its inputs are given)")
        return predict_kitti(
            checkpoint,
            data_dir,
            out_dir,
            split=split,
            batch_size=batch_size,
            device=device,
            runtime=runtime,
            chunk=chunk,
            overwrite=overwrite,
        )
    if batch_size < 1:
        raise ConfigError(f"batch size must be at least 1, got {batch_size}")
    if chosen.ratios:
        ratio = float(chosen.default_ratio if missing_ratio is None else missing_ratio)
        if not 0.0 < ratio < 1.0:
            raise ConfigError(f"missing ratio must be in (0, 1), got {ratio}")
    elif missing_ratio is not None:
        raise ConfigError(
            f"the {chosen.name} protocol takes no missing ratio (its inputs are given)"
        )
    else:
        ratio = None
    checkpoint = resolve_checkpoint(checkpoint)
    refuse_overlap(out_dir, [data_dir, checkpoint], flag="prediction folder")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ConfigError(
            f"prediction folder {out_dir} is a file; name a folder for the predictions"
        )
    check_protocol_data(chosen, data_dir)
    replaced = check_prediction_folder(out, data_dir, split, chosen.name, overwrite)
    clouds = load_split(data_dir, split)
    if len(clouds) == 0:
        raise DataError(f"split {split!r} of {data_dir} has no samples")
    partials = None
    if chosen.input == "given":
        from pfnet.data.benchmarks import load_partials

        partials = load_partials(data_dir, split, len(clouds))
    loaded = load_generator(checkpoint, runtime=runtime, device=device)
    model, config, device = loaded.model, loaded.config, loaded.device
    frame = getattr(config, "frame", "shape")
    n_input = int(model.n_points) - int(model.n_missing)
    files = run_files(clouds.category, clouds.name, chosen.suffixes)
    open_prediction_folder(
        out, files, split, {"name": chosen.name}, data_dir=data_dir, replaced=replaced
    )
    n_predicted = 0
    skipped: list[str] = []
    skipped_keys: set[str] = set()
    for start in range(0, len(clouds), chunk):
        stop = min(start + chunk, len(clouds))
        keys = [
            chosen.sample_keys(str(c), str(n))
            for c, n in zip(clouds.category[start:stop], clouds.name[start:stop], strict=True)
        ]
        if partials is not None:
            rows = []  # (scan, its normalisation, key); a degenerate scan is skipped, named
            for p, k in zip(partials[start:stop], keys, strict=True):
                try:
                    rows.append((p, input_frame(p, frame, f"{k[0]} (partial scan)"), k[0]))
                except DataError as err:
                    skipped.append(str(err))
                    skipped_keys.add(k[0])
                    (out / f"{k[0]}.npy").unlink(missing_ok=True)  # no earlier run's file
            if not rows:
                continue
            batch = np.stack([network_input(t.apply(p), n_input) for p, t, _ in rows])
            detail = predict_missing(model, batch, batch_size, device)
            for (p, t, k), d in zip(rows, detail, strict=True):
                save_npy(out / f"{k}.npy", np.concatenate([p, t.invert(d)]).astype(np.float32))
            n_predicted = int(detail.shape[1])
            continue
        for view in range(chosen.views):
            crops = shapenet_crop(np.asarray(clouds.points[start:stop]), ratio, view)
            # a scan-frame model sees each crop in its own frame, mapped back after
            frames = [None if frame == "shape" else input_frame(c, frame) for c in crops]
            batch = np.stack(
                [
                    network_input(c if f is None else f.apply(c), n_input)
                    for c, f in zip(crops, frames, strict=True)
                ]
            )
            detail = predict_missing(model, batch, batch_size, device)
            for c, f, d, k in zip(crops, frames, detail, keys, strict=True):
                d = d if f is None else f.invert(d)
                save_npy(out / f"{k[view]}.npy", np.concatenate([c, d]).astype(np.float32))
            n_predicted = int(detail.shape[1])
    if len(skipped) == len(clouds):
        raise DataError(
            f"no shape of split {split!r} of {data_dir} could be completed ({skipped[0]})"
        )
    return write_record(
        out,
        describe(checkpoint),
        data_dir,
        split,
        run_files(clouds.category, clouds.name, chosen.suffixes, skipped=skipped_keys),
        loaded.runtime,
        device,
        protocol={
            "name": chosen.name,
            "missing_ratio": ratio,
            "n_points": int(clouds.n_points),
            "views": chosen.views,
            "input": "given partial scan" if partials is not None else "PoinTr's 2,048-point crop",
        },
        model={
            "name": config.model,
            "n_points": config.n_points,
            "missing_ratio": config.missing_ratio,
            "n_input": n_input,
            "n_predicted": n_predicted,
        },
        n_samples=len(clouds) * chosen.views - len(skipped),
        skipped=skipped[:MAX_SKIPPED_LISTED],
        n_skipped=len(skipped),
    )


def predict_kitti(
    checkpoint: str | os.PathLike[str] | None,
    data_dir: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
    split: str = "test",
    batch_size: int = 32,
    device: str = "auto",
    runtime: str = "auto",
    chunk: int = 256,
    overwrite: bool = False,
) -> dict:
    """Complete every KITTI car of a data set prepared from the KITTI layout.

    Each car's input is :func:`pfnet.data.kitti.kitti_input`: its LiDAR points normalised by
    its box as PoinTr's ``NormalizeObjectPose`` does (centred, facing +x, one unit long, y
    up), at most 2,048 of them. As ``pfnet complete`` does, the input is normalised again to
    the unit ball (centroid, max radius), resampled to the model's partial size (IFPS, or
    cyclic repetition), and the predicted missing region mapped back. The completion, in
    PoinTr's normalised frame (where PoinTr's ``KITTI_metric.py`` scores it; nothing is
    mapped back to the sensor frame), is the input followed by the prediction:
    ``PRED/<category>/<name>.npy``.

    Returns:
        The ``predictions.json`` document.

    Raises:
        ConfigError: Bad device or batch size.
        DataError: Unreadable checkpoint or data set; a data set without KITTI's boxes; a
            prediction folder of another run without ``overwrite``
            (:func:`check_prediction_folder`).
    """
    from pfnet.data import load_split
    from pfnet.data.benchmarks import load_partials
    from pfnet.data.kitti import KITTI_INPUT_POINTS, kitti_input, load_boxes
    from pfnet.inference.predict import network_input
    from pfnet.inference.runtimes import load_generator
    from pfnet.inference.shipped import describe, resolve_checkpoint
    from pfnet.io.clouds import save_npy
    from pfnet.io.files import refuse_overlap

    if batch_size < 1:
        raise ConfigError(f"batch size must be at least 1, got {batch_size}")
    checkpoint = resolve_checkpoint(checkpoint)
    refuse_overlap(out_dir, [data_dir, checkpoint], flag="prediction folder")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ConfigError(
            f"prediction folder {out_dir} is a file; name a folder for the predictions"
        )
    check_protocol_data(get_protocol("kitti"), data_dir)
    replaced = check_prediction_folder(out, data_dir, split, "kitti", overwrite)
    cars = load_split(data_dir, split)
    if len(cars) == 0:
        raise DataError(f"split {split!r} of {data_dir} has no samples")
    boxes = load_boxes(data_dir, split, len(cars))
    partials = load_partials(data_dir, split, len(cars))
    keys = [f"{c}/{n}" for c, n in zip(cars.category, cars.name, strict=True)]
    inputs = [kitti_input(p, b, k) for p, b, k in zip(partials, boxes, keys, strict=True)]
    loaded = load_generator(checkpoint, runtime=runtime, device=device)
    model, config, device = loaded.model, loaded.config, loaded.device
    frame = getattr(config, "frame", "shape")
    n_input = int(model.n_points) - int(model.n_missing)
    files = run_files(cars.category, cars.name)
    open_prediction_folder(
        out, files, split, {"name": "kitti"}, data_dir=data_dir, replaced=replaced
    )
    n_predicted = 0
    for start in range(0, len(cars), chunk):
        stop = min(start + chunk, len(cars))
        given = inputs[start:stop]
        transforms = [_car_normalisation(p, frame) for p in given]
        batch = np.stack(
            [network_input(t.apply(p), n_input) for p, t in zip(given, transforms, strict=True)]
        )
        detail = predict_missing(model, batch, batch_size, device, source=checkpoint)
        for p, t, d, k in zip(given, transforms, detail, keys[start:stop], strict=True):
            save_npy(out / f"{k}.npy", np.concatenate([p, t.invert(d)]).astype(np.float32))
        n_predicted = int(detail.shape[1])
    return write_record(
        out,
        describe(checkpoint),
        data_dir,
        split,
        files,
        loaded.runtime,
        device,
        protocol={
            "name": "kitti",
            "missing_ratio": None,
            "n_points": None,
            "views": 1,
            "input": f"the car's points, PoinTr's NormalizeObjectPose, at most "
            f"{KITTI_INPUT_POINTS} (IFPS)",
            "frame": "PoinTr's normalised object frame (y up, facing +x, one unit long)",
        },
        model={
            "name": config.model,
            "n_points": config.n_points,
            "missing_ratio": config.missing_ratio,
            "n_input": n_input,
            "n_predicted": n_predicted,
        },
        n_samples=len(cars),
    )


def _car_normalisation(points: np.ndarray, frame: str = "scan"):
    """The unit ball of a pose-normalised car, as ``complete`` normalises a scan (turned to
    its main horizontal axis for an ``aligned`` model); for a car whose points all coincide
    (a single LiDAR return), a ball of radius 0.5 around them, half the car's length in this
    frame."""
    from pfnet.data.sampling import unit_ball
    from pfnet.data.scan_frame import ScanFrame
    from pfnet.inference.predict import input_frame

    if unit_ball(points) is None:
        centre = np.asarray(points, np.float64).mean(axis=0)
        return ScanFrame(centre=centre, radius=0.5, rotation=np.eye(3))
    return input_frame(points, frame)
