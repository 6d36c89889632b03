"""Inputs that change while pfnet reads them (issue 36, class 1).

Binary bodies are read, never memory-mapped: a mapped file truncated after its size was
checked killed the process with SIGBUS (exit 135, no message, the other inputs lost).
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from pfnet.errors import DataError
from pfnet.io import formats
from pfnet.io.clouds import read_point_cloud, write_ply

POINTS = np.random.default_rng(0).normal(size=(5000, 3)).astype(np.float32)


def _npy(path):
    np.save(path, np.hstack([POINTS, POINTS]).astype(np.float64))


def _npy_fortran(path):
    np.save(path, np.asfortranarray(np.hstack([POINTS, POINTS])))


def _ply(path):
    write_ply(path, POINTS)


def _ply_faces_first(path):
    faces = b"".join(b"\x03" + np.array([0, 1, 2], "<i4").tobytes() for _ in range(100))
    header = (
        b"ply\nformat binary_little_endian 1.0\nelement face 100\n"
        b"property list uchar int vertex_indices\n"
        b"element vertex %d\nproperty float x\nproperty float y\nproperty float z\n"
        b"end_header\n" % len(POINTS)
    )
    path.write_bytes(header + faces + POINTS.astype("<f4").tobytes())


def _pcd(path):
    header = (
        "VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {len(POINTS)}\nHEIGHT 1\nPOINTS {len(POINTS)}\nDATA binary\n"
    )
    path.write_bytes(header.encode() + POINTS.astype("<f4").tobytes())


WRITERS = {
    "a.npy": _npy,
    "f.npy": _npy_fortran,
    "a.ply": _ply,
    "faces.ply": _ply_faces_first,
    "a.pcd": _pcd,
}


@pytest.mark.parametrize("name", sorted(WRITERS))
def test_every_binary_reader_gives_the_same_points(tmp_path, name):
    path = tmp_path / name
    WRITERS[name](path)
    np.testing.assert_array_equal(read_point_cloud(path), POINTS)


@pytest.mark.parametrize("name", sorted(WRITERS))
def test_a_file_truncated_after_its_size_check_is_refused_by_name(tmp_path, monkeypatch, name):
    path = tmp_path / name
    WRITERS[name](path)
    opened = formats.FileBody.__init__

    def open_then_truncate(self, fh, file):
        opened(self, fh, file)
        os.truncate(path, os.path.getsize(path) // 2)  # after the size was taken

    monkeypatch.setattr(formats.FileBody, "__init__", open_then_truncate)
    with pytest.raises(DataError, match=rf"{name}: the file changed while pfnet read it"):
        read_point_cloud(path)


def test_a_truncated_input_does_not_kill_the_process(tmp_path):
    """In a process of its own: what was a SIGBUS is one line, and the next input is read."""
    for name in ("big.ply", "next.ply"):
        _ply(tmp_path / name)
    script = textwrap.dedent(
        f"""
        import os
        from pfnet.io import formats
        from pfnet.errors import DataError
        from pfnet.io.clouds import read_point_cloud
        opened = formats.FileBody.__init__
        def open_then_truncate(self, fh, file):
            opened(self, fh, file)
            if file.name == "big.ply":
                os.truncate(file, 300)
        formats.FileBody.__init__ = open_then_truncate
        for name in ("big.ply", "next.ply"):
            try:
                print(name, len(read_point_cloud(os.path.join({str(tmp_path)!r}, name))))
            except DataError as err:
                print("error:", err)
        """
    )
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    assert "big.ply: the file changed while pfnet read it" in done.stdout
    assert f"next.ply {len(POINTS)}" in done.stdout


def test_no_reader_maps_a_file():
    """The mechanism itself: nothing under pfnet.io.formats memory-maps an input."""
    for path in Path(formats.__file__).parent.glob("*.py"):
        text = path.read_text(encoding="utf-8")
        assert "memmap" not in text and "mmap_mode" not in text, path.name
