"""Paths whose bytes are not UTF-8, and folders nested too deep (issue 36, class 2).

Under a real ``en_US.UTF-8`` locale Python's streams are strict (``C.UTF-8`` escapes and hid
the bug); ``PYTHONIOENCODING=utf-8:strict`` gives a child process the same streams.
"""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pfnet.data.sources import meshes
from pfnet.errors import DataError
from pfnet.io.paths import shown, walk_files

LATIN1 = os.fsdecode(b"caf\xe9")  # 'caf\udce9': a Latin-1 name as Python holds it


def _pfnet(*args, cwd):
    env = {**os.environ, "PYTHONIOENCODING": "utf-8:strict", "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, "-m", "pfnet.cli", *args],
        capture_output=True,
        cwd=cwd,
        env=env,
        timeout=600,
    )


def test_shown_escapes_the_bytes_that_are_not_utf8():
    assert shown(LATIN1) == "caf\\xe9"
    assert shown("café") == "café"
    assert shown(Path(LATIN1) / "x") == "caf\\xe9/x"


def test_the_cli_prints_such_paths_escaped(monkeypatch):
    from pfnet.cli import main

    streams = {}
    for name in ("stdout", "stderr"):  # strict, as under en_US.UTF-8
        streams[name] = io.TextIOWrapper(io.BytesIO(), encoding="utf-8", errors="strict")
        monkeypatch.setattr(sys, name, streams[name])
    assert main(["render", f"{LATIN1}.ply", "--out", f"{LATIN1}.png"]) == 1
    streams["stderr"].flush()
    assert b"caf\\xe9.ply" in streams["stderr"].buffer.getvalue()
    assert streams["stderr"].errors == "strict"  # restored after the command


def _meshes_folder(root: Path) -> None:
    for category in ("chair", "table"):
        (root / category).mkdir(parents=True)
        for i in range(3):
            np.savetxt(root / category / f"s{i}.xyz", np.random.default_rng(i).random((300, 3)))
    (root / "chair" / "s0.xyz").rename(root / "chair" / f"{LATIN1}.xyz")
    obj = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"
    (root / "table" / f"{LATIN1}.obj").write_text(obj)


def test_prepare_reads_latin1_names_and_writes_the_manifest(tmp_path):
    _meshes_folder(tmp_path / "meshes")
    out = f"data-{LATIN1}"
    done = _pfnet(
        "prepare", "meshes", "--out", out, "--workers", "1", "--points", "64", cwd=tmp_path
    )
    assert done.returncode == 0, done.stderr.decode(errors="replace")
    assert b"data-caf\\xe9" in done.stdout  # the path printed, escaped
    assert b"skipped" not in done.stdout  # both Latin-1 files were read (trimesh, the seed)
    manifest = json.loads((tmp_path / out / "manifest.json").read_text(encoding="utf-8"))
    assert manifest  # ASCII JSON; a stored name reads back to the same bytes


def test_complete_to_a_latin1_out(tmp_path):
    np.savetxt(tmp_path / "scan.xyz", np.random.default_rng(0).random((2000, 3)))
    done = _pfnet("complete", "scan.xyz", "--out", f"out-{LATIN1}", cwd=tmp_path)
    assert done.returncode == 0, done.stderr.decode(errors="replace")
    assert b"out-caf\\xe9" in done.stdout
    assert (tmp_path / f"out-{LATIN1}" / "scan_completed.ply").is_file()


def _deep(root: Path, levels: int) -> Path:
    root.mkdir(parents=True)
    deep = root
    for _ in range(levels):  # one at a time: mkdir(parents=True) itself recurses
        deep = deep / "d"
        deep.mkdir()
    (deep / "s.xyz").write_text("0 0 0\n1 0 0\n0 1 0\n")
    return deep


def _remove_deep(deep: Path, root: Path) -> None:
    """Remove what :func:`_deep` made, bottom up (shutil.rmtree recurses too)."""
    (deep / "s.xyz").unlink()
    while deep != root:
        deep.rmdir()
        deep = deep.parent


def test_walk_files_bounds_the_depth_without_recursion(tmp_path):
    _deep(tmp_path / "shallow", 3)
    assert walk_files(tmp_path / "shallow") == [
        tmp_path.joinpath("shallow", "d", "d", "d", "s.xyz")
    ]
    deep = _deep(tmp_path / "deep" / "chair", 1500)  # rglob died in a RecursionError here
    try:
        with pytest.raises(DataError, match=r"nest more than 64 levels deep"):
            walk_files(tmp_path / "deep")
        with pytest.raises(DataError, match=r"nest more than 64 levels deep"):
            meshes.scan(tmp_path / "deep")
    finally:
        _remove_deep(deep, tmp_path / "deep" / "chair")


def test_walk_files_leaves_out_hidden_files_and_follows_no_folder_link(tmp_path):
    (tmp_path / "a" / ".hidden").mkdir(parents=True)
    (tmp_path / "a" / ".hidden" / "x.xyz").write_text("0 0 0\n")
    (tmp_path / "a" / "y.xyz").write_text("0 0 0\n")
    (tmp_path / "a" / "loop").symlink_to(tmp_path / "a")
    assert walk_files(tmp_path / "a") == [tmp_path / "a" / "y.xyz"]


def test_predict_and_evaluate_with_latin1_data_and_out(tmp_path):
    pytest.importorskip("onnxruntime")  # the shipped model runs on either runtime
    from pfnet.data import prepare_dataset

    data, pred = f"data-{LATIN1}", f"pred-{LATIN1}"
    prepare_dataset(None, tmp_path / data, format="procedural", points=2048, seed=0, count=3,
                    categories=["chair", "table"], workers=1, progress=False)  # fmt: skip
    done = _pfnet("predict", "--data", data, "--out", pred, "--device", "cpu", cwd=tmp_path)
    assert done.returncode == 0, done.stderr.decode(errors="replace")
    assert b"pred-caf\\xe9" in done.stdout and b"--data data-caf\\xe9" in done.stdout
    done = _pfnet("evaluate", pred, "--data", data, cwd=tmp_path)
    assert done.returncode == 0, done.stderr.decode(errors="replace")
    assert b"pred-caf\\xe9 vs data-caf\\xe9" in done.stdout
