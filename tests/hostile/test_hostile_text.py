"""Hostile text files: `.xyz` and ASCII PLY are read a block of lines at a time, so memory
follows the points a file holds, not its lines; an overlong line is refused by number; the
lines after a PLY's vertices are never read (the sixth audit: a 60 MB tail of twenty million
short lines took 2.2 GB, one 400-million-token line 5.2 GB)."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from pfnet.errors import DataError
from pfnet.formats.lines import MAX_LINE_BYTES
from pfnet.io import read_point_cloud

PLY_HEADER = (
    "ply\nformat ascii 1.0\nelement vertex {n}\n"
    "property float x\nproperty float y\nproperty float z\nend_header\n"
)


def test_an_overlong_line_is_refused_by_number(tmp_path: Path) -> None:
    long = "1 " * (MAX_LINE_BYTES // 2 + 10) + "\n"
    xyz = tmp_path / "long.xyz"
    xyz.write_text("0 0 0\n1 1 1\n" + long)
    with pytest.raises(DataError, match=r"long\.xyz: line 3 is longer than 65536 bytes"):
        read_point_cloud(xyz)
    ply = tmp_path / "long.ply"
    ply.write_text(PLY_HEADER.format(n=2) + "0 0 0\n" + long)
    with pytest.raises(DataError, match=r"long\.ply: line 9 is longer than"):  # file lines
        read_point_cloud(ply)


def test_lines_after_the_ply_vertices_are_not_read(tmp_path: Path) -> None:
    ply = tmp_path / "tail.ply"
    tail = "12\n" * 100_000 + "x" * (4 * MAX_LINE_BYTES) + "\n\xff\xfe not text"
    ply.write_text(PLY_HEADER.format(n=3) + "1 2 3\n4 5 6\n7 8 9\n" + tail, encoding="latin-1")
    np.testing.assert_array_equal(read_point_cloud(ply), [[1, 2, 3], [4, 5, 6], [7, 8, 9]])


def test_an_ascii_ply_claiming_more_vertices_than_it_has_is_truncated(tmp_path: Path) -> None:
    ply = tmp_path / "short.ply"
    ply.write_text(PLY_HEADER.format(n=19_000_000) + "1 2 3\n4 5 6\n")
    tracemalloc.start()
    try:
        with pytest.raises(DataError, match="truncated PLY data"):
            read_point_cloud(ply)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 50e6  # nothing of the claimed 19 million rows was allocated


@pytest.mark.parametrize("kind", ["xyz", "ply"])
def test_text_readers_use_memory_in_proportion_to_the_points(tmp_path: Path, kind: str) -> None:
    n = 300_000
    rows = "12 34 56\n" * n
    path = tmp_path / f"many.{kind}"
    path.write_text((PLY_HEADER.format(n=n) if kind == "ply" else "") + rows)
    tracemalloc.start()
    try:
        points = read_point_cloud(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert points.shape == (n, 3)
    # about 60 bytes a point now (float64 blocks, their join, the float32 result); reading
    # the lines as Python strings took 360
    assert peak < 100 * n, f"{peak / n:.0f} bytes a point"


def test_text_points_with_uneven_columns_and_comments_still_read(tmp_path: Path) -> None:
    path = tmp_path / "mixed.xyz"
    path.write_text(
        "\ufeffx,y,z\n# comment\n0,0,0\n1 1 1 0.5 0.5 0.5\n\n// note\n2\t2\t2 # after\n3, 3, 3\n"
    )
    np.testing.assert_array_equal(
        read_point_cloud(path), [[0, 0, 0], [1, 1, 1], [2, 2, 2], [3, 3, 3]]
    )
    bad = tmp_path / "bad.xyz"
    bad.write_text("0 0 0\n" * 70_000 + "1 1_0 1\n")  # the bad line in the second block
    with pytest.raises(DataError, match=r"line 70001 is not numeric: '1 1_0 1'"):
        read_point_cloud(bad)
    count = tmp_path / "count.pts"
    count.write_text("7\n")
    with pytest.raises(DataError, match="line 1 has 1 column"):
        read_point_cloud(count)
