"""The files and folders pfnet writes: atomic writes and the checks every command makes on
its outputs before it changes anything (an output inside an input, an input overwritten, a
report in the wrong place of a prediction folder, a folder that is another kind of output).

:func:`atomic_path` is the one way pfnet writes a file: a crash never leaves half of one.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Iterable, Iterator
from pathlib import Path

from pfnet.errors import ConfigError
from pfnet.io.formats import POINT_CLOUD_SUFFIXES

__all__ = [
    "atomic_path",
    "check_report_path",
    "other_kind",
    "output_path",
    "refuse_input_overwrite",
    "refuse_overlap",
]


def refuse_overlap(
    out: str | os.PathLike[str], inputs: Iterable[str | os.PathLike[str]], *, flag: str = "output"
) -> None:
    """Refuse an output location that is, contains or lies inside one of ``inputs``.

    Every command checks this before it changes anything: writing into (or replacing) a
    folder that holds the inputs could overwrite or delete them. Symbolic links are
    resolved, so another spelling of the same place is caught too.

    Raises:
        ConfigError: Naming the flag, the output and the input it overlaps.
    """
    target = Path(out).resolve()
    for item in inputs:
        source = Path(item).resolve()
        if target == source:
            relation = "is"
        elif source.is_relative_to(target):
            relation = "contains"
        elif target.is_relative_to(source):
            relation = "is inside"
        else:
            continue
        raise ConfigError(
            f"{flag} {out} {relation} the input {item}; "
            "write the output to a place apart from the inputs"
        )


def other_kind(folder: str | os.PathLike[str]) -> str | None:
    """What pfnet output ``folder`` already is (a data set, a prediction folder, a training
    run), or None: a command that writes a folder of its own kind refuses these."""
    folder = Path(folder)
    if (folder / "manifest.json").is_file():
        return "a prepared data set"
    if (folder / "predictions.json").is_file():
        return "a prediction folder"
    if (folder / "last.pt").is_file() or (folder / "best.pt").is_file():
        return "a training run"
    return None


def refuse_input_overwrite(
    outputs: Iterable[str | os.PathLike[str]],
    inputs: Iterable[str | os.PathLike[str]],
    *,
    flag: str = "output",
) -> None:
    """Refuse output files that are input files, folders, devices or pipes, before any work.

    Raises:
        ConfigError: Naming the output and the input it would replace.
    """
    sources = {Path(item).resolve(): item for item in inputs}
    for output in outputs:
        path = Path(output)
        if path.is_dir():
            raise ConfigError(f"{flag}: {path} is a folder; name a file to write")
        if path.exists() and not path.is_file() and not path.is_symlink():
            # what is written replaces what is there: never a device or a pipe
            raise ConfigError(f"{flag}: {path} exists and is not a regular file")
        if path.resolve() in sources:
            raise ConfigError(
                f"{flag}: writing {path} would overwrite the input "
                f"{sources[path.resolve()]}; choose another output"
            )


def check_report_path(
    output: str | os.PathLike[str],
    pred_dir: str | os.PathLike[str],
    inputs: Iterable[str | os.PathLike[str]],
    *,
    flag: str,
    categories: Iterable[str] = (),
) -> None:
    """Refuse a report or picture path that would replace part of a command's inputs.

    Nothing may be written inside or over ``inputs`` (data sets, checkpoints); inside the
    prediction folder ``pred_dir`` a report goes directly in it (the subfolders are the
    categories') and may replace an earlier report, never be named as a point cloud file
    (existing or to come), a category folder (existing or to come, from ``categories``),
    the ``predictions.json`` record or a hidden file.

    Raises:
        ConfigError: Naming the flag and the file.
    """
    refuse_input_overwrite([output], [], flag=flag)  # not a folder, a device or a pipe
    for item in inputs:
        if Path(item).is_file():
            refuse_input_overwrite([output], [item], flag=flag)
        else:
            refuse_overlap(output, [item], flag=flag)
    target = Path(output).resolve()
    folder = Path(pred_dir).resolve()
    if target.is_relative_to(folder):
        # whether or not it exists yet: predict writes its predictions after this check
        if target.parent != folder:
            raise ConfigError(
                f"{flag}: {output} is inside a subfolder of the prediction folder {pred_dir}, "
                "which holds the categories' predictions; write it in the folder or elsewhere"
            )
        if (
            target.suffix.lower() in POINT_CLOUD_SUFFIXES
            or target.name == "predictions.json"
            or target.name.startswith(".")
            or target.name in set(categories)
        ):
            raise ConfigError(
                f"{flag}: writing {output} would overwrite a file of the prediction folder "
                f"{pred_dir}; choose another name"
            )


def output_path(out: str | os.PathLike[str]) -> Path:
    """``out`` with its folder resolved as the output checks see it ("new/../x.png" makes no
    "new") and its last part kept: a symbolic link there is replaced, never written through."""
    out = Path(out)
    return out.parent.resolve() / out.name


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` that replaces ``path`` when the block succeeds.

    The temporary name lives in the same folder (so :func:`os.replace` is atomic) and keeps
    the suffix of ``path`` (so writers that pick a format from the suffix, such as
    ``np.save`` or matplotlib's ``savefig``, behave as they would on ``path``). If the block
    raises, the temporary file is removed and ``path`` is left untouched; an ``OSError`` that
    names no file (a full disk) or the temporary one is made to name ``path``.

    Args:
        path: The final destination; its parent folder must exist.

    Yields:
        The temporary path to write to.
    """
    final = Path(path)
    if final.exists() and not final.is_file() and not final.is_symlink():
        # os.replace would put a file where a device or a pipe was (a link is replaced by
        # the file, its target left alone: pfnet never writes through a link)
        raise ConfigError(f"{final} exists and is not a regular file; pfnet will not replace it")
    tmp = final.with_name(f".{final.stem}.{secrets.token_hex(6)}.tmp{final.suffix}")
    try:
        yield tmp
        os.replace(tmp, final)
    except BaseException as err:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        if isinstance(err, OSError) and err.filename in (None, str(tmp)):
            # a full disk names no file (or the temporary one, which is gone): name the output
            err.filename = str(final)
        raise
