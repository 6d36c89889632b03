"""The record ``predictions.json`` of a prediction folder: written by ``pfnet predict``,
read by ``pfnet evaluate`` (strictly: a record it cannot trust is an error) and by ``predict
--overwrite`` (leniently: a record it cannot read is no record of pfnet's).

It names the checkpoint, data set, split (and its file's digest), protocol and model of the
run, and lists the files the run wrote (:func:`run_files`), the only ones ``--overwrite``
removes (:mod:`pfnet.evaluation.prediction_folder`).
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Collection, Sequence
from pathlib import Path
from typing import Any

from pfnet.errors import DataError
from pfnet.evaluation.protocols import PROTOCOLS

# The most a predictions.json may take; its readers (read_record, read_record_or_none) refuse
# a larger one. The names of the files its run wrote are its bulk, each shape's name listed once
# with the endings of its views: 53 KB for PCN's test split (1,200 shapes), 0.46 MB for
# ShapeNet-55's (10,432 shapes, 83,456 files), 1.8 MB for its train split. 8 MB of the
# shortest names took 0.8 s and 104 MiB to read. A run whose list would not fit records
# none, and --overwrite refuses its folder.
MAX_RECORD_BYTES = 8 << 20


# What pfnet predict leaves in a prediction folder besides its category folders: the record
# and a record whose atomic write was interrupted; in a category folder besides the files the
# record lists, a prediction whose atomic write (pfnet.io.files.atomic_path) was interrupted.
RECORD = "predictions.json"
RECORD_TMP = re.compile(r"\.predictions\.[0-9a-f]{12}\.tmp\.json")
PREDICTION_TMP = re.compile(r"\.(.+)\.[0-9a-f]{12}\.tmp\.npy")


def plain_file(path: Path) -> bool:
    """A regular file, not a link to one."""
    return path.is_file() and not path.is_symlink()


def is_name_list(value: Any) -> bool:
    """A JSON list of strings."""
    return isinstance(value, list) and all(isinstance(n, str) for n in value)


def run_files(
    categories: Sequence[Any],
    names: Sequence[Any],
    suffixes: Sequence[str] = ("",),
    *,
    skipped: Collection[str] = (),
) -> dict[str, Any]:
    """The ``files`` a prediction run records: it writes ``<category>/<name><ending>`` for each
    shape (``<category>/<name>`` not in ``skipped``) and each ending (``<suffix>.npy``, one
    per view of the protocol: :attr:`pfnet.evaluation.protocols.Protocol.suffixes`), in a folder for
    each category.

    Returns:
        ``{"endings": [...], "names": {category: [sorted names]}}``; ``--overwrite`` removes
        only these files (:func:`pfnet.evaluation.prediction_folder.check_prediction_folder`).
    """
    listed: dict[str, list[str]] = {str(category): [] for category in categories}
    for category, name in zip(categories, names, strict=True):
        if f"{category}/{name}" not in skipped:
            listed[str(category)].append(str(name))
    return {
        "endings": [f"{suffix}.npy" for suffix in suffixes],
        "names": {category: sorted(listed[category]) for category in sorted(listed)},
    }


def read_record_or_none(record: Path) -> Any:
    """A ``predictions.json`` document, None if it cannot be read or passes
    :data:`MAX_RECORD_BYTES`."""
    try:
        if not plain_file(record) or record.stat().st_size > MAX_RECORD_BYTES:
            return None
        return json.loads(record.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):
        return None


def recorded_run(info: Any) -> dict[str, Any] | None:
    """The data set, split and protocol a ``predictions.json`` document records, None if it
    records none (the data set None in an unfinished record of an older pfnet, which did not
    name it)."""
    if not isinstance(info, dict) or not isinstance(info.get("protocol"), dict):
        return None
    name = info["protocol"].get("name", "test")
    return {"data": info.get("data"), "split": info.get("split"), "protocol": name}


def recorded_files(info: dict[str, Any]) -> tuple[dict[str, set[str]], list[str]] | None:
    """The names listed under each category folder and the endings of a record's ``files``
    (:func:`run_files`), None when it lists none: records of pfnet versions before it did,
    and of runs whose list would pass :data:`MAX_RECORD_BYTES`."""
    files = info.get("files")
    if not isinstance(files, dict) or not isinstance(files.get("names"), dict):
        return None
    names, endings = files["names"], files.get("endings")
    views = max(p.views for p in PROTOCOLS.values())
    if not (
        is_name_list(endings)
        and 1 <= len(endings) <= views
        and all(e.endswith(".npy") for e in endings)
        and all(map(is_name_list, names.values()))
    ):
        return None
    return {category: set(listed) for category, listed in names.items()}, endings


def write_record_file(out: Path, info: dict[str, Any], indent: int | None) -> dict[str, Any]:
    """Write ``info`` as ``out/predictions.json``, atomically; its ``files`` None when listing
    them would pass :data:`MAX_RECORD_BYTES` (``--overwrite`` then refuses the folder)."""
    from pfnet.io.files import atomic_path

    text = json.dumps(info, indent=indent) + "\n"
    if len(text.encode("utf-8")) > MAX_RECORD_BYTES:
        info = {**info, "files": None}
        text = json.dumps(info, indent=indent) + "\n"
    with atomic_path(out / RECORD) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return info


def read_record(pred_dir: str | os.PathLike[str]) -> dict[str, Any] | None:
    """``PRED/predictions.json``, checked by :func:`_record_problem`, or None without one."""
    record = Path(pred_dir) / RECORD
    if not record.exists() and not record.is_symlink():
        return None
    if not record.is_file():  # a folder here was once taken for no record at all
        raise DataError(f"cannot read {record}: not a file")
    if record.stat().st_size > MAX_RECORD_BYTES:  # predict lists its files within the bound
        raise DataError(
            f"cannot read {record}: larger than {MAX_RECORD_BYTES >> 20} MB, not pfnet "
            "predict's record"
        )
    try:
        info = json.loads(record.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError) as err:
        # ValueError: bad UTF-8 or JSON; RecursionError: forged nesting
        raise DataError(f"cannot read {record} ({type(err).__name__}: {str(err)[:120]})") from None
    problem = _record_problem(info)
    if problem is not None:
        raise DataError(f"{record}: {problem}")
    if info.get("complete") is False:
        raise DataError(
            f"{record} says its prediction run stopped before writing every file (the "
            "folder may mix old and new predictions); run pfnet predict again"
        )
    return info


def _record_problem(info: Any) -> str | None:
    """What is wrong with a ``predictions.json`` document, or None.

    Types are exact, as :func:`pfnet.inference.predict.predict_split` writes them: a string
    ``"false"`` is not a boolean, ``"0.25"`` not a ratio, ``true`` not a count (``bool`` is an
    ``int`` to Python). Keys that older pfnet versions did not write (``complete``,
    ``n_points``, ``model``) may be absent.
    """
    from pfnet.models.config import is_int, is_number

    def shown(value: Any) -> str:
        return json.dumps(value)[:40] if not isinstance(value, float) else repr(value)

    if not isinstance(info, dict):
        return f"expected a JSON object, got {type(info).__name__}"
    if not isinstance(info.get("complete", False), bool):
        return f'"complete" must be true or false, got {shown(info["complete"])}'
    if not isinstance(info.get("split"), str):
        return f'"split" must be a split\'s name, got {shown(info.get("split"))}'
    digest = info.get("split_sha256", "0" * 64)  # older records have none
    if not (isinstance(digest, str) and re.fullmatch(r"[0-9a-f]{64}", digest)):
        return f'"split_sha256" must be a SHA-256 in hex, got {shown(digest)}'
    protocol = info.get("protocol")
    if not isinstance(protocol, dict):
        return f'"protocol" must be an object, got {shown(protocol)}'
    name = protocol.get("name", "test")  # "test": PF-Net's protocol, as older records name it
    if not isinstance(name, str):
        return f'"protocol.name" must be a protocol\'s name, got {shown(name)}'
    from pfnet.evaluation.protocols import PROTOCOL_NAMES, PROTOCOLS
    from pfnet.io.formats import MAX_CLOUD_POINTS

    if name != "test" and name.lower() not in PROTOCOL_NAMES:
        return (
            f'"protocol.name" must be one of test, {", ".join(PROTOCOL_NAMES)}, got {shown(name)}'
        )
    benchmark = name not in ("test", "pfnet")
    ratio = protocol.get("missing_ratio")
    # A benchmark protocol with given inputs (pcn) records no ratio.
    if not (ratio is None and benchmark or is_number(ratio) and 0 < ratio < 1):
        return f'"protocol.missing_ratio" must be a number in (0, 1), got {shown(ratio)}'
    model = info.get("model", {})
    if not isinstance(model, dict):
        return f'"model" must be an object, got {shown(model)}'
    counts = {
        "protocol.n_points": protocol.get("n_points"),
        "model.n_points": model.get("n_points"),
        "model.n_input": model.get("n_input"),
        "model.n_predicted": model.get("n_predicted"),
    }
    # informational, but bounded as every count pfnet reads: no cloud holds more points
    for key, count in counts.items():
        if count is not None and not (is_int(count) and 1 <= count <= MAX_CLOUD_POINTS):
            return (
                f'"{key}" must be a positive integer of at most {MAX_CLOUD_POINTS}, '
                f"got {shown(count)}"
            )
    views, most = protocol.get("views"), max(p.views for p in PROTOCOLS.values())
    if views is not None and not (is_int(views) and 1 <= views <= most):
        return f'"protocol.views" must be a positive integer of at most {most}, got {shown(views)}'
    points, trained = counts["protocol.n_points"], counts["model.n_points"]
    # Benchmark protocols resample their clouds to the model's input, as complete does.
    if not benchmark and None not in (points, trained) and points != trained:
        return (
            f"its model was trained on clouds of {trained} points but predicted clouds of "
            f"{points}: the scores would compare regions of different sizes"
        )
    return None


def recorded_protocol(
    pred_dir: str | os.PathLike[str],
) -> tuple[str, float | None, int | None] | None:
    """The split, missing ratio and points per cloud ``PRED/predictions.json`` records (the
    points ``None`` in records of older pfnet versions, the ratio ``None`` for a protocol
    with given inputs), or None without a record.

    Predictions made by ``pfnet predict`` record their split and crop; scoring them with
    another crop compares each prediction with the wrong missing region, silently.

    Raises:
        DataError: If the record exists but cannot be read.
    """
    info = read_record(pred_dir)
    if info is None:
        return None
    protocol = info["protocol"]
    ratio = protocol.get("missing_ratio")
    return info["split"], None if ratio is None else float(ratio), protocol.get("n_points")


def recorded_data_problem(
    pred_dir: str | os.PathLike[str], data_dir: str | os.PathLike[str], split: str
) -> str | None:
    """Why ``PRED/predictions.json`` says its predictions come from other clouds than the
    ``split`` of ``data_dir`` (the digest of the split file differs), or None (the same
    clouds, or a record without a digest or of another split, which other checks report).

    Raises:
        DataError: If the record exists but cannot be read.
    """
    from pfnet.data.digests import split_digest

    info = read_record(pred_dir)
    if info is None or info["split"] != split or "split_sha256" not in info:
        return None
    if split_digest(data_dir, split) == info["split_sha256"]:
        return None
    made_from = info.get("data") if isinstance(info.get("data"), str) else "another data set"
    return (
        f"{pred_dir} was predicted from other {split} clouds than those of {data_dir} (the "
        f"digest its predictions.json records differs; made from {made_from[:200]!r}): score "
        "it against the data set it was predicted on, or pass --ignore-recorded-protocol"
    )


def recorded_protocol_name(pred_dir: str | os.PathLike[str]) -> str | None:
    """The protocol name ``PRED/predictions.json`` records (``pfnet`` for records of older
    pfnet versions, which name it ``test``), or None without a record.

    Raises:
        DataError: If the record exists but cannot be read.
    """
    info = read_record(pred_dir)
    if info is None:
        return None
    name = info["protocol"].get("name", "test")
    return "pfnet" if name == "test" else str(name)
