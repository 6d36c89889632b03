"""Running a trained model over a data set split with the deterministic test protocol.

``pfnet predict`` is the command around :func:`predict_split`; ``complete`` uses
:func:`predict_missing`. Output of :func:`predict_split`, ready for ``pfnet evaluate``::

    PRED/<category>/<name>.npy    float32 (M, 3): the predicted missing region
    PRED/predictions.json         checkpoint, data, split, protocol, model, files written
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Collection, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pfnet.errors import ConfigError, DataError
from pfnet.protocols import PROTOCOLS, check_protocol_data, get_protocol

# A prediction is in the frame of its partial cloud normalised to the unit ball, where the true
# missing region lies within radius 1 and a working model's points stay within a few radii.
# A point a thousand radii out is no completion but a broken or forged model (weights that
# overflow, a graph that outputs 1e30), and mapped back it could leave float32.
MAX_PREDICTED_RADIUS = 1e3
# Skipped shapes named in predictions.json.
MAX_SKIPPED_LISTED = 100
# The most a predictions.json may take; its readers (here and in pfnet.evaluation) refuse a
# larger one. The names of the files its run wrote are its bulk, each shape's name listed once
# with the endings of its views: 53 KB for PCN's test split (1,200 shapes), 0.46 MB for
# ShapeNet-55's (10,432 shapes, 83,456 files), 1.8 MB for its train split. 8 MB of the
# shortest names took 0.8 s and 104 MiB to read. A run whose list would not fit records
# none, and --overwrite refuses its folder.
MAX_RECORD_BYTES = 8 << 20


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


# What pfnet predict leaves in a prediction folder besides its category folders: the record
# and a record whose atomic write was interrupted; in a category folder besides the files the
# record lists, a prediction whose atomic write (pfnet.io.atomic_path) was interrupted.
_RECORD = "predictions.json"
_RECORD_TMP = re.compile(r"\.predictions\.[0-9a-f]{12}\.tmp\.json")
_PREDICTION_TMP = re.compile(r"\.(.+)\.[0-9a-f]{12}\.tmp\.npy")


def check_prediction_folder(
    out: Path, data_dir: str | os.PathLike[str], split: str, protocol: str, overwrite: bool
) -> list[Path]:
    """Refuse a prediction folder that holds another run's predictions, unless ``overwrite``.

    A run is its data set, split and protocol (the name ``predictions.json`` records; ``test``
    for the pfnet protocol). A folder of the same run is predicted again as it is, file by
    file; one of another run would mix two runs' files under the new record. With
    ``overwrite`` its old predictions are removed by :func:`open_prediction_folder`: exactly
    the files its record lists (:func:`run_files`), and their category folders, and only when
    the folder holds nothing else (interrupted writes of those files aside).

    Returns:
        The files, then the category folders, to remove before predicting (none for the same
        run).

    Raises:
        DataError: Another run's folder without ``overwrite``; with it, a folder whose record
            cannot be read or does not list its files, or that holds files it does not list.
    """
    out = Path(out)
    record = out / _RECORD
    _SEEN[out.resolve()] = _record_stamp(out)  # open_prediction_folder compares it
    if not out.is_dir() or (not record.exists() and not record.is_symlink()):
        return []  # new, or files of the user's: predictions are added beside them
    this = {"data": str(Path(data_dir).resolve()), "split": split, "protocol": protocol}
    info = _read_record(record)
    recorded = _recorded_run(info)
    if recorded is not None and recorded["data"] is None:  # a record of an older pfnet
        this["data"] = None
    if recorded == this:
        return []
    if not overwrite:
        shown = (
            "an unreadable predictions.json"
            if recorded is None
            else ", ".join(f"{key} {value}" for key, value in recorded.items())
        )
        raise DataError(
            f"{out} holds the predictions of another run ({shown}); pass --overwrite to "
            "replace them, or name another folder"
        )
    if recorded is None:
        raise DataError(
            f"{out}: its {_RECORD} cannot be read, so it is not a folder pfnet predict wrote; "
            "overwriting only replaces one"
        )
    listed = _recorded_files(info)
    if listed is None:
        folders = sorted(info["categories"]) if _names(info.get("categories")) else []
        where = f" (it names the category folders {_shown(folders)})" if folders else ""
        raise DataError(
            f"{out}: its {_RECORD} does not list the files of its predictions (older pfnet "
            "versions, and runs of more files than a record holds, do not), so which files "
            f"they are is not known; remove them yourself{where} or choose another "
            "prediction folder"
        )
    stems, endings = listed

    def is_listed(category: str, file: Path) -> bool:
        name = file.name
        if (interrupted := _PREDICTION_TMP.fullmatch(name)) is not None:
            name = f"{interrupted.group(1)}.npy"
        return _plain_file(file) and any(
            name.endswith(ending) and name[: -len(ending)] in stems[category] for ending in endings
        )

    files, folders, others = [], [], []
    for entry in sorted(out.iterdir()):
        if entry.name == _RECORD or (_RECORD_TMP.fullmatch(entry.name) and _plain_file(entry)):
            continue
        if entry.name not in stems or not _plain_folder(entry):
            others.append(entry.name)
            continue
        for file in sorted(entry.iterdir()):
            if is_listed(entry.name, file):
                files.append(file)
            else:
                others.append(f"{entry.name}/{file.name}")
        folders.append(entry)
    if others:
        raise _unlisted(out, others)
    return files + folders


def _unlisted(out: Path, others: list[str]) -> DataError:
    return DataError(
        f"{out} holds files its {_RECORD} does not list ({_shown(others)}); --overwrite "
        "replaces only a folder of nothing but the listed files, so move these out first or "
        "choose another prediction folder"
    )


def _shown(names: list[str]) -> str:
    return ", ".join(names[:3]) + (", ..." if len(names) > 3 else "")


def _plain_file(path: Path) -> bool:
    return path.is_file() and not path.is_symlink()


def _plain_folder(path: Path) -> bool:
    return path.is_dir() and not path.is_symlink()


def _names(value: Any) -> bool:
    return isinstance(value, list) and all(isinstance(n, str) for n in value)


def _read_record(record: Path) -> Any:
    """A ``predictions.json`` document, None if it cannot be read or passes
    :data:`MAX_RECORD_BYTES`."""
    try:
        if not _plain_file(record) or record.stat().st_size > MAX_RECORD_BYTES:
            return None
        return json.loads(record.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):
        return None


def _recorded_run(info: Any) -> dict[str, Any] | None:
    """The data set, split and protocol a ``predictions.json`` document records, None if it
    records none (the data set None in an unfinished record of an older pfnet, which did not
    name it)."""
    if not isinstance(info, dict) or not isinstance(info.get("protocol"), dict):
        return None
    name = info["protocol"].get("name", "test")
    return {"data": info.get("data"), "split": info.get("split"), "protocol": name}


def _recorded_files(info: dict[str, Any]) -> tuple[dict[str, set[str]], list[str]] | None:
    """The names listed under each category folder and the endings of a record's ``files``
    (:func:`run_files`), None when it lists none: records of pfnet versions before it did,
    and of runs whose list would pass :data:`MAX_RECORD_BYTES`."""
    files = info.get("files")
    if not isinstance(files, dict) or not isinstance(files.get("names"), dict):
        return None
    names, endings = files["names"], files.get("endings")
    views = max(p.views for p in PROTOCOLS.values())
    if not (
        _names(endings)
        and 1 <= len(endings) <= views
        and all(e.endswith(".npy") for e in endings)
        and all(map(_names, names.values()))
    ):
        return None
    return {category: set(listed) for category, listed in names.items()}, endings


def run_files(
    categories: Sequence[Any],
    names: Sequence[Any],
    suffixes: Sequence[str] = ("",),
    *,
    skipped: Collection[str] = (),
) -> dict[str, Any]:
    """The ``files`` a prediction run records: it writes ``<category>/<name><ending>`` for each
    shape (``<category>/<name>`` not in ``skipped``) and each ending (``<suffix>.npy``, one
    per view of the protocol: :attr:`pfnet.protocols.Protocol.suffixes`), in a folder for
    each category.

    Returns:
        ``{"endings": [...], "names": {category: [sorted names]}}``; ``--overwrite`` removes
        only these files (:func:`check_prediction_folder`).
    """
    listed: dict[str, list[str]] = {str(category): [] for category in categories}
    for category, name in zip(categories, names, strict=True):
        if f"{category}/{name}" not in skipped:
            listed[str(category)].append(str(name))
    return {
        "endings": [f"{suffix}.npy" for suffix in suffixes],
        "names": {category: sorted(listed[category]) for category in sorted(listed)},
    }


def open_prediction_folder(
    out: Path,
    files: dict[str, Any],
    split: str,
    protocol: dict[str, Any],
    *,
    data_dir: str | os.PathLike[str],
    replaced: Sequence[Path] = (),
) -> None:
    """Make ``out`` and the category folders of ``files`` (:func:`run_files`), with a
    ``predictions.json`` that lists them and says the run is not complete (``evaluate``
    refuses it until the last file is written).

    The files and then the folders ``replaced`` (another run's, :func:`check_prediction_folder`)
    are removed first, then the record is written: an interrupted run never leaves another
    run's files beside its record, and the old record, which lists those left, stays until
    then.

    ``out`` stays locked for this run until :func:`write_record`; another run holding it, or
    having written a record since :func:`check_prediction_folder` saw the folder, is refused.

    Raises:
        DataError: A category folder is a link out of ``out``; a folder ``replaced`` holds a
            file put there since it was checked; another predict run writes, or wrote, into
            ``out``.
    """
    categories = list(files["names"])
    for category in categories:
        folder = out / category
        # a folder that is a symbolic link (or resolves elsewhere) would take the
        # predictions outside out: into the data set, over a checkpoint
        if folder.is_symlink() or (
            folder.exists() and not folder.resolve().is_relative_to(out.resolve())
        ):
            raise DataError(
                f"{folder} is a link out of the prediction folder {out}; remove it first"
            )
    out.mkdir(parents=True, exist_ok=True)
    _lock(out)
    if _record_stamp(out) != _SEEN.get(out.resolve(), _record_stamp(out)):
        _unlock(out)
        raise DataError(
            f"another pfnet predict wrote into {out} while this one ran; this run wrote "
            "nothing: run it again when the other has finished"
        )
    for path in replaced:  # each file, then its folder, as check_prediction_folder found them
        if not _plain_folder(path):
            path.unlink(missing_ok=True)
            continue
        try:
            path.rmdir()
        except FileNotFoundError:
            pass
        except OSError:
            added = sorted(f"{path.name}/{file.name}" for file in path.iterdir())
            if not added:
                raise
            raise _unlisted(out, added) from None
    record = {
        "complete": False,
        "data": str(Path(data_dir).resolve()),
        "split": split,
        "protocol": protocol,
        "categories": sorted(categories),
        "files": files,  # the files --overwrite may remove
    }
    _write_record(out, record, indent=None)
    for category in categories:
        (out / category).mkdir(exist_ok=True)


# The record each prediction folder had when checked, and the folders this process writes
# into, each locked (flock on the folder) from open_prediction_folder to write_record: two
# predict runs into one folder once both reported success over a mix of their files.
_SEEN: dict[Path, tuple[int, int] | None] = {}
_LOCKS: dict[Path, int] = {}


def _record_stamp(out: Path) -> tuple[int, int] | None:
    """The inode and modification time of ``out``'s record (each write replaces the file)."""
    try:
        stat = (out / _RECORD).stat()
    except OSError:
        return None
    return stat.st_ino, stat.st_mtime_ns


def _lock(out: Path) -> None:
    """Take the prediction folder ``out`` for this run, or refuse if another run has it."""
    import fcntl

    key = out.resolve()
    _unlock(out)  # a run of this process that failed half-way
    fd = os.open(key, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise DataError(
            f"another pfnet predict is writing into {out}; wait for it, or name another folder"
        ) from None
    _LOCKS[key] = fd


def _unlock(out: Path) -> None:
    fd = _LOCKS.pop(out.resolve(), None)
    if fd is not None:
        os.close(fd)


def _write_record(out: Path, info: dict[str, Any], indent: int | None) -> dict[str, Any]:
    """Write ``info`` as ``out/predictions.json``, atomically; its ``files`` None when listing
    them would pass :data:`MAX_RECORD_BYTES` (``--overwrite`` then refuses the folder)."""
    from pfnet.io import atomic_path

    text = json.dumps(info, indent=indent) + "\n"
    if len(text.encode("utf-8")) > MAX_RECORD_BYTES:
        info = {**info, "files": None}
        text = json.dumps(info, indent=indent) + "\n"
    with atomic_path(out / _RECORD) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return info


def write_record(
    out: Path,
    checkpoint: Any,
    data_dir: str | os.PathLike[str],
    split: str,
    files: dict[str, Any],
    runtime: str,
    device: str,
    *,
    protocol: dict[str, Any],
    model: dict[str, Any],
    n_samples: int,
    **extra: Any,
) -> dict[str, Any]:
    """Write the ``predictions.json`` of a finished prediction run into ``out``; returns it.

    It names the checkpoint, data set, split (and its file's digest), the category folders,
    the protocol and the model; ``extra`` keys (``skipped``...) come after the sample count,
    and last the files the run wrote (:func:`run_files`; which ``--overwrite`` may remove).
    """
    from pfnet.data.format import split_digest
    from pfnet.shipped import describe

    info = {
        "complete": True,
        "checkpoint": describe(checkpoint),
        "data": str(Path(data_dir).resolve()),
        "split": split,
        "split_sha256": split_digest(data_dir, split),  # evaluate refuses other clouds
        "categories": sorted(files["names"]),
        "protocol": protocol,
        "model": model,
        "n_samples": n_samples,
        **extra,
        "device": device,
        "runtime": runtime,
        "files": files,
    }
    try:
        return _write_record(out, info, indent=2)
    finally:
        _unlock(out)


def predict_missing(
    model: Any, partial: np.ndarray, batch_size: int, device: str, *, source: Any = "in use"
) -> np.ndarray:
    """Run ``model`` over ``partial`` clouds in batches, checking each batch's output.

    Args:
        model: A completion model in eval mode (``forward(partial) -> Completion``), or an
            :class:`pfnet.runtimes.OnnxGenerator` (which runs without torch).
        partial: float32 ``(S, n, 3)`` partial clouds.
        batch_size: Clouds per forward pass.
        device: Torch device the model lives on.
        source: The checkpoint the PyTorch model came from, named in errors (an ONNX model
            names its own file).

    Returns:
        float32 ``(S, M, 3)`` predicted missing regions.

    Raises:
        DataError: The model's output is not ``(batch, M, 3)`` finite points
            (:func:`check_detail`), or an ONNX model fails to run.
    """
    from pfnet.runtimes import OnnxGenerator

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
        runtime: ``auto``, ``torch`` or ``onnx`` (:func:`pfnet.runtimes.load_generator`).
        overwrite: Replace another run's predictions in ``out_dir``.

    Returns:
        The ``predictions.json`` document.

    Raises:
        ConfigError: Bad device, batch size or ratio.
        DataError: Unreadable checkpoint or data set, clouds of another size than the model's,
            or a model output refused by :func:`check_detail`.
    """
    from pfnet.data import load_split, test_protocol_crop
    from pfnet.io import refuse_overlap, save_npy
    from pfnet.runtimes import load_generator
    from pfnet.shipped import resolve_checkpoint

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
    detail = predict_missing(
        model, np.asarray(partial, dtype=np.float32), batch_size, device, source=checkpoint
    )

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
        checkpoint,
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
        },
        model={
            "name": config.model,
            "n_points": config.n_points,
            "missing_ratio": trained_ratio,
            "n_predicted": int(detail.shape[1]),
        },
        n_samples=len(clouds),
    )


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
      (:func:`pfnet.protocols.shapenet_crop`), already in the data set's unit ball, reduced
      to the model's partial size by IFPS; the completion is the 2,048 input points followed
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
    from pfnet.completion import network_input, normalisation
    from pfnet.data import load_split
    from pfnet.io import refuse_overlap, save_npy
    from pfnet.protocols import get_protocol, shapenet_crop
    from pfnet.runtimes import load_generator
    from pfnet.shipped import resolve_checkpoint

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
                    rows.append((p, normalisation(p, f"{k[0]} (partial scan)"), k[0]))
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
            batch = np.stack([network_input(c, n_input) for c in crops])
            detail = predict_missing(model, batch, batch_size, device)
            for c, d, k in zip(crops, detail, keys, strict=True):
                save_npy(out / f"{k[view]}.npy", np.concatenate([c, d]).astype(np.float32))
            n_predicted = int(detail.shape[1])
    if len(skipped) == len(clouds):
        raise DataError(
            f"no shape of split {split!r} of {data_dir} could be completed ({skipped[0]})"
        )
    return write_record(
        out,
        checkpoint,
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
    from pfnet.completion import network_input
    from pfnet.data import load_split
    from pfnet.data.benchmarks import load_partials
    from pfnet.data.kitti import KITTI_INPUT_POINTS, kitti_input, load_boxes
    from pfnet.io import refuse_overlap, save_npy
    from pfnet.runtimes import load_generator
    from pfnet.shipped import resolve_checkpoint

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
    n_input = int(model.n_points) - int(model.n_missing)
    files = run_files(cars.category, cars.name)
    open_prediction_folder(
        out, files, split, {"name": "kitti"}, data_dir=data_dir, replaced=replaced
    )
    n_predicted = 0
    for start in range(0, len(cars), chunk):
        stop = min(start + chunk, len(cars))
        given = inputs[start:stop]
        transforms = [_car_normalisation(p) for p in given]
        batch = np.stack(
            [network_input(t.apply(p), n_input) for p, t in zip(given, transforms, strict=True)]
        )
        detail = predict_missing(model, batch, batch_size, device, source=checkpoint)
        for p, t, d, k in zip(given, transforms, detail, keys[start:stop], strict=True):
            save_npy(out / f"{k}.npy", np.concatenate([p, t.invert(d)]).astype(np.float32))
        n_predicted = int(detail.shape[1])
    return write_record(
        out,
        checkpoint,
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


def _car_normalisation(points: np.ndarray):
    """The unit ball of a pose-normalised car, as ``complete`` normalises a scan; for a car
    whose points all coincide (a single LiDAR return), a ball of radius 0.5 around them, half
    the car's length in this frame."""
    from pfnet.data.sampling import Normalisation, unit_ball

    transform = unit_ball(points)
    if transform is None:
        return Normalisation(centre=np.asarray(points, np.float64).mean(axis=0), radius=0.5)
    return transform
