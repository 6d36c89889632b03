"""The on-disk dataset format shared by ``pfnet prepare``, training, ``predict`` and ``evaluate``.

A dataset is a folder (DESIGN.md §3)::

    DIR/manifest.json   format name and version, points per shape, source, seed, per-split
                        per-category counts, licence/credit lines, skipped files
    DIR/train.npz       points float32 (S, N, 3), category (S,) str, name (S,) str
    DIR/val.npz         the same; always written, possibly with S = 0
    DIR/test.npz        the same

Names are unique in the whole dataset and filesystem safe (``[a-z0-9._-]``), so
``PRED/<category>/<name>.npy`` is a valid path for every shape. A dataset is written into a
sibling folder ``DIR.tmp-<pid>`` and renamed onto ``DIR`` only when every file is complete,
so an interrupted run never leaves a folder that looks like a finished dataset.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import unicodedata
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pfnet.data.archives import check_members, write_npz
from pfnet.data.digests import remember_digest
from pfnet.data.temporaries import remove_stale_temporaries, replace_through_temporary
from pfnet.errors import DataError

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "MANIFEST_NAME",
    "SPLITS",
    "CloudSet",
    "check_output",
    "load_split",
    "read_manifest",
    "skipped_entries",
    "split_categories",
    "write_dataset",
]

FORMAT_NAME = "pfnet-completion-dataset"
FORMAT_VERSION = 1
MANIFEST_NAME = "manifest.json"
# A manifest lists shapes' credits and skipped files: well under a megabyte for 820 models.
MAX_MANIFEST_BYTES = 16 << 20
# Skipped files a manifest names (a partial PCN download skips thousands): the rest are
# counted, so that a manifest stays far below MAX_MANIFEST_BYTES.
MAX_SKIPPED_LISTED = 1000
_MAX_SKIPPED_CHARS = 300
SPLITS: tuple[str, ...] = ("train", "val", "test")
# What follows a split's name in the files of a data set: the split, and the side files of
# the benchmarks (pfnet.data.benchmarks, pfnet.data.kitti).
SIDE_FILE_ENDINGS = (".npz", ".partial.npz", ".boxes.npz")


def skipped_entries(skipped: list[tuple[str, str]]) -> dict:
    """The manifest's ``skipped`` list: the first :data:`MAX_SKIPPED_LISTED` ``(path,
    reason)`` pairs, each cut to 300 characters, and ``skipped_not_listed``, the count of the
    rest, when there are more."""
    listed = [
        {"path": path[:_MAX_SKIPPED_CHARS], "reason": reason[:_MAX_SKIPPED_CHARS]}
        for path, reason in skipped[:MAX_SKIPPED_LISTED]
    ]
    entries: dict = {"skipped": listed}
    if len(skipped) > MAX_SKIPPED_LISTED:
        entries["skipped_not_listed"] = len(skipped) - MAX_SKIPPED_LISTED
    return entries


RECORD_NAME = "predictions.json"
"""The record ``pfnet predict`` writes in a prediction folder beside the category folders: no
category or shape may take its name."""


def unsafe_component(text: str) -> str | None:
    """Why ``text`` cannot be one file or folder name under an output folder, or None.

    Categories and names become paths (``PRED/<category>/<name>.npy``), so a data set
    holding ``..``, ``/`` or an absolute path could make a command write outside its
    ``--out``; they are refused when a split is loaded. So are names beginning with ``.``,
    which ``evaluate`` would never find (it skips hidden and temporary files).
    """
    if not text:
        return "is empty"
    if text in (".", ".."):
        return "is not a name"
    if len(text) > 200:
        return "is longer than 200 characters"
    if len(text.encode("utf-8", "surrogatepass")) > 200:  # file names are 255 bytes at most
        return "is longer than 200 bytes in UTF-8"
    bad = sorted({c for c in text if c in "/\\:" or ord(c) < 32 or ord(c) == 127})
    if bad:
        return f"contains {', '.join(repr(c) for c in bad)}: not allowed in a file name"
    if not text.strip():
        return "is only spaces"
    # Format characters (right-to-left overrides, zero-width joiners...) make a file name
    # display as another one
    hidden = sorted({c for c in text if unicodedata.category(c) == "Cf"})
    if hidden:
        return f"contains the invisible {', '.join(repr(c) for c in hidden)}"
    if text == RECORD_NAME:  # pfnet prepare never makes one (safe_name renames it)
        return "is the name of the record predict writes beside the category folders"
    if text.startswith("."):  # pfnet prepare never makes one (safe_name strips the dot)
        return (
            "begins with '.': a hidden file, which evaluate skips like the temporary files "
            "pfnet writes"
        )
    return None


def _folded(text: str) -> str:
    """``text`` as case- and normalisation-insensitive file systems compare names (``é``
    composed or not, ``Chair`` and ``chair``: one file)."""
    return unicodedata.normalize("NFD", unicodedata.normalize("NFD", text).casefold())


@dataclass(frozen=True)
class CloudSet:
    """The shapes of one split.

    Attributes:
        points: float32 ``(S, N, 3)`` complete clouds, centred and scaled into the unit ball.
        category: ``(S,)`` str category of each shape.
        name: ``(S,)`` str unique, filesystem-safe name of each shape.
        extra: float32 ``(S, E, 3)`` more points of each shape's surface, in the same
            coordinates (``pfnet prepare --pool N`` stores ``E = N - points``), or ``None``.
            With ``points`` they form the pool that training draws fresh clouds from.
    """

    points: np.ndarray
    category: np.ndarray
    name: np.ndarray
    extra: np.ndarray | None = None

    def __post_init__(self) -> None:
        points, category, name = self.points, self.category, self.name
        if points.ndim != 3 or points.shape[2] != 3 or points.dtype != np.float32:
            raise DataError(
                f"points must be a float32 (S, N, 3) array, got {points.dtype} {points.shape}"
            )
        for label, array in (("category", category), ("name", name)):
            if array.ndim != 1 or array.shape[0] != points.shape[0] or array.dtype.kind != "U":
                raise DataError(
                    f"{label} must be a str array of shape ({points.shape[0]},), "
                    f"got {array.dtype} {array.shape}"
                )
        for label, array in (("category", category), ("name", name)):
            for value in array:
                problem = unsafe_component(str(value))
                if problem:
                    raise DataError(f"{label} {str(value)!r} {problem}")
        pairs = {(_folded(c), _folded(n)) for c, n in zip(category.tolist(), name.tolist())}
        if len(pairs) != len(name):  # equal, or one file on a case-insensitive file system
            seen: dict[tuple[str, str], tuple[str, str]] = {}
            for pair in zip(category.tolist(), name.tolist(), strict=True):
                key = (_folded(pair[0]), _folded(pair[1]))
                if key in seen:
                    if seen[key] == pair:
                        raise DataError(f"shape {pair[0]}/{pair[1]} appears twice in the split")
                    raise DataError(
                        f"shapes {'/'.join(seen[key])} and {'/'.join(pair)} differ only in case "
                        "or Unicode normalisation: one file on macOS and Windows file systems"
                    )
                seen[key] = pair
        finite = np.isfinite(points).all(axis=(1, 2))
        if not finite.all():  # named here, not by the geometry call that would meet it later
            i = int(np.argmin(finite))
            raise DataError(
                f"shape {category[i]}/{name[i]} (index {i}) holds NaN or infinite coordinates"
            )
        folded: dict[str, str] = {}
        for cat in sorted(set(category.tolist())):
            other = folded.setdefault(_folded(cat), cat)
            if other != cat:
                raise DataError(
                    f"categories {other} and {cat} differ only in case or Unicode "
                    "normalisation: one folder on macOS and Windows file systems"
                )
        extra = self.extra
        if extra is not None and (
            extra.ndim != 3
            or extra.shape[0] != points.shape[0]
            or extra.shape[2] != 3
            or extra.dtype != np.float32
        ):
            raise DataError(
                f"extra must be a float32 ({points.shape[0]}, E, 3) array, "
                f"got {extra.dtype} {extra.shape}"
            )

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_points(self) -> int:
        """Points per shape, ``N``."""
        return int(self.points.shape[1])

    @property
    def categories(self) -> list[str]:
        """The distinct categories, sorted."""
        return sorted({str(c) for c in self.category})

    @property
    def pool_size(self) -> int:
        """Points per shape in the pool (``N`` when there are no extra points)."""
        return self.n_points + (0 if self.extra is None else int(self.extra.shape[1]))

    def subset(self, index: np.ndarray | list[int] | slice) -> CloudSet:
        """The shapes at ``index`` (an index array, a boolean mask or a slice), in that order."""
        extra = None if self.extra is None else self.extra[index]
        return CloudSet(self.points[index], self.category[index], self.name[index], extra)

    @classmethod
    def empty(cls, n_points: int, pool: int = 0) -> CloudSet:
        """A split without shapes, ``(0, n_points, 3)`` (and ``(0, pool - n_points, 3)``)."""
        extra = np.zeros((0, pool - n_points, 3), np.float32) if pool > n_points else None
        return cls(
            np.zeros((0, n_points, 3), np.float32), np.zeros(0, "<U1"), np.zeros(0, "<U1"), extra
        )


def read_manifest(root: str | os.PathLike[str]) -> dict:
    """Read and check ``ROOT/manifest.json``.

    Args:
        root: A dataset folder written by ``pfnet prepare``.

    Returns:
        The manifest as a dict (see the module docstring).

    Raises:
        DataError: The folder or its manifest is missing, unreadable or of another format.
    """
    folder = Path(root)
    path = folder / MANIFEST_NAME
    if not folder.is_dir():
        raise DataError(f"{folder}: no such dataset folder")
    if not path.is_file():
        raise DataError(f"{folder}: not a pfnet dataset (no {MANIFEST_NAME}; run `pfnet prepare`)")
    if path.stat().st_size > MAX_MANIFEST_BYTES:  # 48 MB of JSON took 555 MB to parse
        raise DataError(f"{path}: larger than {MAX_MANIFEST_BYTES >> 20} MB; not a manifest")
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError) as err:  # RecursionError: forged nesting
        raise DataError(f"{path}: cannot read the manifest: {str(err)[:200]}") from None
    listed = manifest.get("categories") if isinstance(manifest, dict) else None
    if listed is not None and not (
        isinstance(listed, list) and all(isinstance(c, str) for c in listed)
    ):  # a string here once switched the check of the splits' categories off
        raise DataError(f"{path}: the manifest's categories must be a list of names")
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT_NAME:
        raise DataError(f"{path}: not a {FORMAT_NAME} manifest")
    version = manifest.get("version")
    if not _is_count(version) or version > FORMAT_VERSION:  # `true` is an int to Python
        raise DataError(
            f"{path}: format version {json.dumps(version)[:40]} is not supported (this pfnet "
            f"reads versions 1 to {FORMAT_VERSION})"
        )
    points = manifest.get("points")
    if points is not None and not _is_count(points):
        # "512" once switched the split files' point check off, -1 made evaluate compare
        # predictions with clouds of -1 points
        raise DataError(
            f"{path}: the manifest's points per cloud must be a positive integer, got "
            f"{json.dumps(points)[:40]}"
        )
    return manifest


def _is_count(value: object) -> bool:
    """A positive ``int`` that is not a ``bool``."""
    return isinstance(value, int) and not isinstance(value, bool) and value >= 1


def split_record(clouds: CloudSet) -> dict[str, object]:
    """The manifest's record of a split: its total and its shapes per category.

    :func:`load_split` checks each split file against this record, so any tool that writes
    a data set with :func:`write_dataset` must record its splits this way.
    """
    counts: dict[str, int] = {}
    for category in clouds.category.tolist():
        counts[str(category)] = counts.get(str(category), 0) + 1
    return {"total": len(clouds), "categories": dict(sorted(counts.items()))}


def split_record_of(manifest: Mapping, split: str, where: Path) -> dict | None:
    """The manifest's record of ``split`` (see :func:`split_record`), checked; ``None``
    when the manifest has no ``splits`` at all (as an early pfnet wrote them)."""
    if "splits" not in manifest:
        return None
    record = manifest["splits"].get(split) if isinstance(manifest["splits"], dict) else None
    total = record.get("total") if isinstance(record, dict) else None
    counts = record.get("categories") if isinstance(record, dict) else None
    if (
        not isinstance(total, int)
        or isinstance(total, bool)
        or total < 0
        or not isinstance(counts, dict)
        or not all(isinstance(n, int) and not isinstance(n, bool) for n in counts.values())
        or sum(counts.values()) != total
    ):
        raise DataError(
            f"{where}: the manifest's record of the {split} split is malformed (expected "
            '{"total": N, "categories": {NAME: COUNT, ...}} with counts adding up to N)'
        )
    return record


def split_categories(root: str | os.PathLike[str], split: str) -> list[str]:
    """The categories of a split, from its manifest record when there is one (cheap)."""
    record = split_record_of(read_manifest(root), split, Path(root) / MANIFEST_NAME)
    if record is not None:
        return sorted(record["categories"])
    return load_split(root, split).categories


def load_split(root: str | os.PathLike[str], split: str) -> CloudSet:
    """Load one split of a dataset into memory.

    Args:
        root: A dataset folder written by ``pfnet prepare``.
        split: ``"train"``, ``"val"`` or ``"test"``.

    Returns:
        The split's :class:`CloudSet`, in the stored order (the order the test protocol uses).

    Raises:
        DataError: Unknown split, missing or malformed file, or one that disagrees with the
            manifest's record of the split.
    """
    if split not in SPLITS:
        raise DataError(f"split must be one of {', '.join(SPLITS)}, got {split!r}")
    manifest = read_manifest(root)
    path = Path(root) / f"{split}.npz"
    if not path.is_file():
        there = path.exists() or path.is_symlink()  # a pipe, a device, a folder, a broken link
        raise DataError(f"{path}: {'not a regular file' if there else 'missing split file'}")
    record = split_record_of(manifest, split, Path(root) / MANIFEST_NAME)
    try:
        # one open file for the checks, the digest and the arrays: what is recorded as read
        # (split_digest) is what was read, even if the data set is replaced meanwhile
        with open(path, "rb") as fh:
            rows = record["total"] if record is not None else None
            check_members(path, rows, manifest.get("points"), source=fh)
            fh.seek(0)
            digest = hashlib.file_digest(fh, "sha256").hexdigest()
            fh.seek(0)
            with np.load(fh, allow_pickle=False) as data:
                missing = {"points", "category", "name"} - set(data.files)
                if missing:
                    raise DataError(f"{path}: missing arrays {', '.join(sorted(missing))}")
                arrays = {key: data[key] for key in ("points", "category", "name")}
                if "extra" in data.files:
                    arrays["extra"] = data["extra"]
    except DataError:
        raise
    except (OSError, ValueError, zipfile.BadZipFile, MemoryError) as err:
        raise DataError(f"{path}: cannot read the split: {err or type(err).__name__}") from err
    try:
        clouds = CloudSet(**arrays)
    except DataError as err:
        raise DataError(f"{path}: {err}") from err
    remember_digest(root, split, digest)
    listed = manifest.get("categories")
    if isinstance(listed, list):
        strays = sorted(set(clouds.categories) - {str(c) for c in listed})
        if strays:
            raise DataError(f"{path}: categories {strays[:3]} are not in the manifest's list")
    if record is not None and split_record(clouds)["categories"] != record["categories"]:
        raise DataError(
            f"{path}: its shapes per category differ from the manifest's record of the split"
        )
    return clouds  # the point count was compared with the manifest by check_members


def check_output(out: str | os.PathLike[str], overwrite: bool) -> Path:
    """Check that a dataset may be written to ``out`` before any work is done.

    Args:
        out: The dataset folder to create.
        overwrite: Whether an existing non-empty folder may be replaced.

    Returns:
        ``out`` as a Path.

    Raises:
        DataError: ``out`` is a file, a non-empty folder and ``overwrite`` is false, or a
            non-empty folder that is not a pfnet data set.
    """
    path = Path(out)
    if path.exists() and not path.is_dir():
        raise DataError(f"{path}: exists and is not a folder")
    if path.is_dir() and any(path.iterdir()):
        if not overwrite:
            raise DataError(f"{path}: already exists and is not empty (asked not to overwrite it)")
        # --overwrite deletes the folder: only ever an earlier data set and nothing else,
        # never a folder of the user's (the source's parent, a home directory, a data set
        # the user added notes to) named by mistake.
        try:
            read_manifest(path)
        except DataError:
            raise DataError(
                f"{path}: is not a pfnet data set (no readable {MANIFEST_NAME}); overwriting "
                "only replaces a folder that pfnet prepare wrote"
            ) from None
        # the splits, and the benchmarks' side files (given partial scans, KITTI's boxes)
        ours = {
            MANIFEST_NAME,
            *(f"{split}{end}" for split in SPLITS for end in SIDE_FILE_ENDINGS),
        }
        others = sorted(p.name for p in path.iterdir() if p.name not in ours)
        if others:
            raise DataError(
                f"{path}: holds files pfnet prepare did not write ({', '.join(others[:3])}"
                f"{', ...' if len(others) > 3 else ''}); overwriting would delete them, so "
                "move them out first or choose another data set folder"
            )
    # Replace the folder a symbolic link names, not the link.
    return path.resolve() if path.is_symlink() else path


def write_dataset(
    out: str | os.PathLike[str],
    splits: Mapping[str, CloudSet],
    manifest: Mapping[str, object],
    *,
    overwrite: bool = False,
    side_files: Mapping[str, Mapping[str, np.ndarray]] | None = None,
) -> Path:
    """Write a dataset folder atomically.

    Everything goes into ``OUT.tmp-<pid>`` first; that folder is renamed onto ``OUT`` once
    complete (an existing ``OUT`` is moved aside and deleted only after the rename).

    Args:
        out: The dataset folder.
        splits: A :class:`CloudSet` for each of ``SPLITS``.
        manifest: The manifest (JSON-serialisable).
        overwrite: Whether an existing non-empty ``out`` may be replaced.
        side_files: More ``.npz`` files to write in the folder, ``{file name: arrays}``
            (a benchmark's given partial scans, :mod:`pfnet.data.benchmarks`).

    Returns:
        ``out`` as a Path.
    """
    from pfnet.io.locks import folder_lock

    path = check_output(out, overwrite)
    if set(splits) != set(SPLITS):
        raise DataError(f"a dataset needs the splits {', '.join(SPLITS)}, got {sorted(splits)}")
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    # replaced: never while a predict, evaluate or train reads it
    held = folder_lock(path, "replacing") if path.is_dir() else contextlib.nullcontext()
    with held:
        return _write_dataset(path, splits, manifest, side_files)


def _write_dataset(path, splits, manifest, side_files) -> Path:
    def fill(tmp: Path) -> None:
        for split in SPLITS:
            cloud_set = splits[split]
            arrays = {
                "points": cloud_set.points,
                "category": cloud_set.category,
                "name": cloud_set.name,
            }
            if cloud_set.extra is not None:
                arrays["extra"] = cloud_set.extra
            write_npz(tmp / f"{split}.npz", arrays)
        for file_name, side_arrays in (side_files or {}).items():
            write_npz(tmp / file_name, side_arrays)
        # ASCII JSON: a file name whose bytes are not UTF-8 is kept as "\\udce9", which reads
        # back to the same name (a UTF-8 file cannot hold it; issue 36)
        text = json.dumps(manifest, indent=2) + "\n"
        (tmp / MANIFEST_NAME).write_text(text, encoding="utf-8")

    replace_through_temporary(path, fill)
    return path
