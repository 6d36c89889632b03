"""A prediction folder, ``PRED/<category>/<name>.npy`` and ``PRED/predictions.json``, as
``pfnet predict`` fills it: what a run may replace, and the lock that keeps two runs apart.

A folder of the same run (data set, split, protocol) is predicted again file by file; one of
another run is refused unless ``overwrite``, which removes exactly the files its record lists
(:mod:`pfnet.evaluation.prediction_record`). From :func:`open_prediction_folder` to
:func:`write_record` the folder is locked (flock), and its record says the run is not
complete, which ``pfnet evaluate`` refuses.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from pfnet.errors import DataError
from pfnet.evaluation.prediction_record import (
    PREDICTION_TMP,
    RECORD,
    RECORD_TMP,
    is_name_list,
    plain_file,
    read_record_or_none,
    recorded_files,
    recorded_run,
    write_record_file,
)


def check_prediction_folder(
    out: Path, data_dir: str | os.PathLike[str], split: str, protocol: str, overwrite: bool
) -> list[Path]:
    """Refuse a prediction folder that holds another run's predictions, unless ``overwrite``.

    A run is its data set, split and protocol (the name ``predictions.json`` records; ``test``
    for the pfnet protocol). A folder of the same run is predicted again as it is, file by
    file; one of another run would mix two runs' files under the new record. With
    ``overwrite`` its old predictions are removed by :func:`open_prediction_folder`: exactly
    the files its record lists (:func:`pfnet.evaluation.prediction_record.run_files`), and their
    category folders, and only when the folder holds nothing else (interrupted writes of
    those files aside).

    Returns:
        The files, then the category folders, to remove before predicting (none for the same
        run).

    Raises:
        DataError: Another run's folder without ``overwrite``; with it, a folder whose record
            cannot be read or does not list its files, or that holds files it does not list.
    """
    out = Path(out)
    record = out / RECORD
    _SEEN[out.resolve()] = _record_stamp(out)  # open_prediction_folder compares it
    if not out.is_dir() or (not record.exists() and not record.is_symlink()):
        return []  # new, or files of the user's: predictions are added beside them
    this = {"data": str(Path(data_dir).resolve()), "split": split, "protocol": protocol}
    info = read_record_or_none(record)
    recorded = recorded_run(info)
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
            f"{out}: its {RECORD} cannot be read, so it is not a folder pfnet predict wrote; "
            "overwriting only replaces one"
        )
    listed = recorded_files(info)
    if listed is None:
        folders = sorted(info["categories"]) if is_name_list(info.get("categories")) else []
        where = f" (it names the category folders {_shown(folders)})" if folders else ""
        raise DataError(
            f"{out}: its {RECORD} does not list the files of its predictions (older pfnet "
            "versions, and runs of more files than a record holds, do not), so which files "
            f"they are is not known; remove them yourself{where} or choose another "
            "prediction folder"
        )
    stems, endings = listed

    def is_listed(category: str, file: Path) -> bool:
        name = file.name
        if (interrupted := PREDICTION_TMP.fullmatch(name)) is not None:
            name = f"{interrupted.group(1)}.npy"
        return plain_file(file) and any(
            name.endswith(ending) and name[: -len(ending)] in stems[category] for ending in endings
        )

    files, folders, others = [], [], []
    for entry in sorted(out.iterdir()):
        if entry.name == RECORD or (RECORD_TMP.fullmatch(entry.name) and plain_file(entry)):
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
        f"{out} holds files its {RECORD} does not list ({_shown(others)}); --overwrite "
        "replaces only a folder of nothing but the listed files, so move these out first or "
        "choose another prediction folder"
    )


def _shown(names: list[str]) -> str:
    return ", ".join(names[:3]) + (", ..." if len(names) > 3 else "")


def _plain_folder(path: Path) -> bool:
    return path.is_dir() and not path.is_symlink()


def open_prediction_folder(
    out: Path,
    files: dict[str, Any],
    split: str,
    protocol: dict[str, Any],
    *,
    data_dir: str | os.PathLike[str],
    replaced: Sequence[Path] = (),
) -> None:
    """Make ``out`` and the category folders of ``files``
    (:func:`~pfnet.evaluation.prediction_record.run_files`), with a ``predictions.json`` that
    lists them and says the run is not complete (``evaluate`` refuses it until the last file
    is written).

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
    _remove_interrupted_writes(out, categories)
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
    write_record_file(out, record, indent=None)
    for category in categories:
        (out / category).mkdir(exist_ok=True)


def _remove_interrupted_writes(out: Path, categories: list[str]) -> None:
    """Remove the temporary files of writes a killed run left (``.name.<12 hex>.tmp.npy``,
    ``.predictions.<12 hex>.tmp.json``, as :func:`pfnet.io.files.atomic_path` names them):
    the folder is locked, so no run is writing them now, and a re-run leaves no hidden files
    behind."""
    folders = [(out, RECORD_TMP)] + [(out / c, PREDICTION_TMP) for c in categories]
    for folder, pattern in folders:
        if not _plain_folder(folder):
            continue
        for entry in folder.iterdir():
            if pattern.fullmatch(entry.name) and plain_file(entry):
                entry.unlink(missing_ok=True)


# The record each prediction folder had when checked, and the folders this process writes
# into, each locked (flock on the folder) from open_prediction_folder to write_record: two
# predict runs into one folder once both reported success over a mix of their files.
_SEEN: dict[Path, tuple[int, int] | None] = {}
_LOCKS: dict[Path, int] = {}


def _record_stamp(out: Path) -> tuple[int, int] | None:
    """The inode and modification time of ``out``'s record (each write replaces the file)."""
    try:
        stat = (out / RECORD).stat()
    except OSError:
        return None
    return stat.st_ino, stat.st_mtime_ns


def _lock(out: Path) -> None:
    """Take the prediction folder ``out`` for this run, or refuse if another run (a predict
    writing it, an evaluate reading it) has it, naming that process (:mod:`pfnet.io.locks`)."""
    from pfnet.io.locks import take

    key = out.resolve()
    _unlock(out)  # a run of this process that failed half-way
    _LOCKS[key] = take(key, "writing predictions into")


def release_folders() -> None:
    """Let go of every prediction folder this process holds: a run that stopped between
    :func:`open_prediction_folder` and :func:`write_record` (Ctrl-C, a refused output) would
    otherwise keep its folder locked against this process's next evaluate or predict."""
    for key in list(_LOCKS):
        os.close(_LOCKS.pop(key))


def _unlock(out: Path) -> None:
    fd = _LOCKS.pop(out.resolve(), None)
    if fd is not None:
        os.close(fd)


def write_record(
    out: Path,
    checkpoint: str,
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

    It names the checkpoint (``checkpoint``, as :func:`pfnet.inference.shipped.describe` names a
    model file), data set, split (and its file's digest), the category folders,
    the protocol and the model; ``extra`` keys (``skipped``...) come after the sample count,
    and last the files the run wrote (:func:`~pfnet.evaluation.prediction_record.run_files`; which
    ``--overwrite`` may remove).
    """
    from pfnet.data.digests import loaded_split_digest

    info = {
        "complete": True,
        "checkpoint": checkpoint,
        "data": str(Path(data_dir).resolve()),
        "split": split,
        # of the bytes predict read, when it read them: evaluate refuses other clouds
        "split_sha256": loaded_split_digest(data_dir, split),
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
        return write_record_file(out, info, indent=2)
    finally:
        _unlock(out)
