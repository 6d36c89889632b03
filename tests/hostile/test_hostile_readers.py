"""The eighth audit's point-cloud readers: every header read is bounded (a 1 GB sparse "line"
took 2.7 GB), PCD COUNTs are bounded (COUNT 10^8 in a 10 KB file took 4.7 GB), LZF is unpacked
in the Rust core in linear time (an 11 MB file took 40 s in Python), a cloud may hold at most
``MAX_CLOUD_POINTS`` points (a sparse 4 KB PLY of 10^8 vertices took 4.7 GB), binary PLY list
rows cost their lists, not their scalars (a 106 MB file ran past 60 s), and text clouds have
the ASCII PLY/PCD line limit (100 MB of blank lines ran past 60 s)."""

from __future__ import annotations

import contextlib
import os
import signal
import struct
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from pfnet import _core
from pfnet.errors import DataError, GeometryError
from pfnet.io.clouds import read_point_cloud
from pfnet.io.formats import MAX_CLOUD_POINTS
from pfnet.io.formats.pcd import MAX_PCD_UNPACKED, MAX_PCD_VALUES
from pfnet.io.formats.ply import MAX_WALKED_LISTS


@contextlib.contextmanager
def _bounded(seconds: int = 20, megabytes: float = 50):
    """Fail if the block runs longer than ``seconds`` or allocates more than ``megabytes``."""

    def expire(*_):
        raise AssertionError(f"still running after {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.alarm(seconds)
    tracemalloc.start()
    try:
        yield
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
    assert peak < megabytes * 1e6, f"{peak / 1e6:.0f} MB"


def _sparse(path: Path, head: bytes, size: int) -> Path:
    """``head`` then zeros up to ``size`` bytes, which take no disk."""
    path.write_bytes(head)
    os.truncate(path, size)
    return path


PCD_XYZ = "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
PLY_XYZ = "property float x\nproperty float y\nproperty float z\n"


def test_first_and_header_lines_of_sparse_gigabytes_are_refused_unread(tmp_path: Path) -> None:
    ply = _sparse(tmp_path / "magic.ply", b"plyx", 2**30)  # no newline for a gigabyte
    with _bounded(), pytest.raises(DataError, match=r"magic\.ply: not a PLY file"):
        read_point_cloud(ply)
    pcd = _sparse(tmp_path / "head.pcd", b"# .PCD v0.7", 2**30)
    with _bounded(), pytest.raises(DataError, match=r"head\.pcd: header line 1 is longer"):
        read_point_cloud(pcd)


def test_pcd_counts_are_bounded_and_ascii_values_after_z_not_parsed(tmp_path: Path) -> None:
    fields = "FIELDS x y z w\nSIZE 4 4 4 4\nTYPE F F F F\nWIDTH 300\nHEIGHT 1\nPOINTS 300\n"
    rows = "".join(f"{i * 0.01} 0.5 0.25 1\n" for i in range(300))
    for mode in ("ascii", "binary", "binary_compressed"):
        path = tmp_path / f"count_{mode}.pcd"
        path.write_text(f"VERSION 0.7\n{fields}COUNT 1 1 1 100000000\nDATA {mode}\n{rows}")
        with (
            _bounded(),
            pytest.raises(
                DataError,
                match=rf"count_{mode}\.pcd: PCD header declares 100000003 values a point .*"
                rf"at most {MAX_PCD_VALUES}",
            ),
        ):
            read_point_cloud(path)
    # A descriptor of 33 values after z (FPFH) is allowed; only x y z are parsed.
    wide = tmp_path / "wide.pcd"
    descriptor = " ".join(["oops"] * 33)  # not even numbers: never parsed
    wide.write_text(
        f"VERSION 0.7\n{fields.replace(' w', ' fpfh')}COUNT 1 1 1 33\nDATA ascii\n"
        + "".join(f"{i} 2 3 {descriptor}\n" for i in range(300))
    )
    points = read_point_cloud(wide)
    assert points.shape == (300, 3) and points[299, 0] == 299


def _lzf_runs(raw: int) -> bytes:
    """The audit's stream: one literal byte, then groups of six distance-1 references of 264
    bytes and a 32-byte literal (about 32 times smaller than ``raw``)."""
    out, n = bytearray([0, 0]), 1
    while raw - n >= 6 * 264 + 32:
        out += b"\xe0\xff\x00" * 6 + bytes([31]) + bytes(32)
        n += 6 * 264 + 32
    while n < raw:
        k = min(32, raw - n)
        out += bytes([k - 1]) + bytes(k)
        n += k
    return bytes(out)


def _lzf_naive(src: bytes) -> bytes:
    """liblzf's decoder, byte by byte: the reference for the Rust one."""
    out, i = bytearray(), 0
    while i < len(src):
        ctrl = src[i]
        i += 1
        if ctrl < 32:
            out += src[i : i + ctrl + 1]
            i += ctrl + 1
            continue
        length = ctrl >> 5
        if length == 7:
            length += src[i]
            i += 1
        ref = len(out) - ((ctrl & 31) << 8) - src[i] - 1
        i += 1
        for k in range(length + 2):
            out.append(out[ref + k])
    return bytes(out)


def test_lzf_overlapping_references_unpack_in_linear_time(tmp_path: Path) -> None:
    rng = np.random.default_rng(14)
    stream = bytearray([31, *rng.integers(0, 256, 32)])
    for _ in range(300):  # references of 3 to 264 bytes from 1 to 32 bytes back
        length = int(rng.integers(1, 8))
        stream += bytes([length << 5, *([rng.integers(256)] if length == 7 else [])])
        stream.append(int(rng.integers(32)))
    stream = bytes(stream)
    expected = _lzf_naive(stream)
    got = _core.lzf_decompress(np.frombuffer(stream, np.uint8), len(expected))
    assert got.dtype == np.uint8 and got.tobytes() == expected

    n = 4_000_000  # 48 MB of coordinates in 1.5 MB: 0.5 s in Rust, minutes byte by byte
    payload = _lzf_runs(12 * n)
    head = f"{PCD_XYZ}WIDTH {n}\nHEIGHT 1\nPOINTS {n}\nDATA binary_compressed\n".encode()
    path = tmp_path / "runs.pcd"
    path.write_bytes(head + struct.pack("<II", len(payload), 12 * n) + payload)
    start = time.perf_counter()
    points = read_point_cloud(path)
    assert points.shape == (n, 3) and not points.any()
    assert time.perf_counter() - start < 10


@pytest.mark.parametrize(
    ("payload", "message"),
    [
        (b"\x05ab", "at byte 0: a literal run of 6 bytes is cut off"),
        (b"\x00a\x20\x04", "at byte 2: a back reference 5 bytes back from byte 1"),
        (b"\x00a\xe0", "at byte 2: a back reference is cut off"),
        (b"\x00a", "the stream ends after 1 of the declared 12 bytes"),
        (b"\x00a\xe0\xff\x00", "at byte 2: expands beyond the declared 12 bytes"),
    ],
)
def test_truncated_and_forged_lzf_streams_name_the_file(
    tmp_path: Path, payload: bytes, message: str
) -> None:
    path = tmp_path / "forged.pcd"  # one point: 12 bytes
    path.write_bytes(
        f"{PCD_XYZ}WIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA binary_compressed\n".encode()
        + struct.pack("<II", len(payload), 12)
        + payload
    )
    with pytest.raises(
        DataError, match=r"forged\.pcd: corrupt PCD binary_compressed data \(LZF data is corrupt"
    ) as err:
        read_point_cloud(path)
    assert message in str(err.value)
    with pytest.raises(GeometryError, match="LZF data is corrupt"):
        _core.lzf_decompress(np.frombuffer(payload, np.uint8), 12)


def test_clouds_beyond_the_point_limit_are_refused_from_their_headers(tmp_path: Path) -> None:
    n = MAX_CLOUD_POINTS + 1
    head = f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\n{PLY_XYZ}end_header\n"
    ply = _sparse(tmp_path / "many.ply", head.encode(), len(head) + 12 * n)  # honest, sparse
    pcd_head = f"{PCD_XYZ}WIDTH {n}\nHEIGHT 1\nPOINTS {n}\nDATA binary\n".encode()
    pcd = _sparse(tmp_path / "many.pcd", pcd_head, len(pcd_head) + 12 * n)
    npy_head = np.lib.format.header_data_from_array_1_0(np.zeros((1, 3), "<f4"))
    npy_head["shape"] = (n, 3)
    npy = tmp_path / "many.npy"
    with open(npy, "wb") as fh:
        np.lib.format.write_array_header_1_0(fh, npy_head)
    os.truncate(npy, npy.stat().st_size + 12 * n)
    for path in (ply, pcd, npy):
        with (
            _bounded(),
            pytest.raises(
                DataError,
                match=rf"{path.name}: declares {n} points; pfnet reads at most 50,000,000",
            ),
        ):
            read_point_cloud(path)
    # binary_compressed: bounded in bytes too, whatever the points
    fields = "FIELDS x y z d\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 100\n"
    m = MAX_PCD_UNPACKED // 412 + 1
    big = tmp_path / "big.pcd"
    big.write_bytes(
        f"VERSION 0.7\n{fields}WIDTH {m}\nHEIGHT 1\nPOINTS {m}\nDATA binary_compressed\n".encode()
        + struct.pack("<II", 100, 412 * m)
        + bytes(100)
    )
    with _bounded(), pytest.raises(DataError, match=r"big\.pcd: .* pfnet unpacks at most"):
        read_point_cloud(big)


def test_binary_clouds_are_converted_to_float32_a_column_at_a_time(tmp_path: Path) -> None:
    n = 1_000_000
    cloud = np.random.default_rng(0).normal(size=(n, 3)).astype("<f4")
    head = f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\n{PLY_XYZ}end_header\n"
    path = tmp_path / "big.ply"
    path.write_bytes(head.encode() + cloud.tobytes())
    with _bounded(megabytes=30):  # the cloud is 12 MB; a float64 stack alone took 24 more
        points = read_point_cloud(path)
    assert points.dtype == np.float32
    np.testing.assert_array_equal(points, cloud)


def test_ply_list_rows_cost_their_lists_not_their_scalars(tmp_path: Path) -> None:
    rows, scalars = 300_000, 40
    props = "".join(f"property uchar a{i}\n" for i in range(scalars))
    head = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {rows}\n{PLY_XYZ}{props}"
        "property list uchar int ids\nend_header\n"
    )
    body = np.zeros(rows, dtype=[("xyz", "<f4", 3), ("a", "u1", scalars), ("n", "u1")])
    body["xyz"] = np.random.default_rng(0).random((rows, 3))
    body["n"][::2] = 0
    path = tmp_path / "wide.ply"
    path.write_bytes(head.encode() + body.tobytes())
    start = time.perf_counter()
    np.testing.assert_array_equal(read_point_cloud(path), body["xyz"])
    assert time.perf_counter() - start < 10  # 0.2 s; 9 s when each scalar was read alone

    # Lists of varying lengths between scalars, before the vertex element too.
    faces = b"".join(struct.pack(f"<bB{k}iB", 7, k, *range(k), 9) for k in (0, 3, 5))
    verts = b"".join(struct.pack("<B2h3f", 2, 1, 2, x, 2 * x, 3 * x) for x in (1.0, 4.0))
    mixed = tmp_path / "mixed.ply"
    mixed.write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement face 3\nproperty char c\n"
        b"property list uchar int ids\nproperty uchar u\nelement vertex 2\n"
        b"property list uchar short l\nproperty float x\nproperty float y\nproperty float z\n"
        b"end_header\n" + faces + verts
    )
    np.testing.assert_array_equal(read_point_cloud(mixed), [[1, 2, 3], [4, 8, 12]])

    # Two lists a row: the bound counts lengths read, refused before any is read.
    lists = MAX_WALKED_LISTS // 2 + 1
    head = (
        f"ply\nformat binary_little_endian 1.0\nelement face {lists}\n"
        "property list uchar int a\nproperty list uchar int b\n"
        f"element vertex 1\n{PLY_XYZ}end_header\n"
    )
    two = _sparse(tmp_path / "two.ply", head.encode(), len(head) + 2 * lists + 12)
    with (
        _bounded(),
        pytest.raises(DataError, match=rf"two\.ply: .* to {2 * lists}; pfnet reads at most"),
    ):
        read_point_cloud(two)


@pytest.mark.parametrize(("name", "filler"), [("blank.xyz", "\n"), ("comment.txt", "#\n")])
def test_text_clouds_count_blank_and_comment_lines(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, name: str, filler: str
) -> None:
    monkeypatch.setattr("pfnet.io.formats.lines.MAX_ASCII_LINES", 1000)
    path = tmp_path / name
    path.write_text("1 2 3\n" * 10 + filler * 1000 + "4 5 6\n")
    with pytest.raises(DataError, match=rf"{name}: more than 1000 lines before the end"):
        read_point_cloud(path)
    path.write_text("1 2 3\n" * 10 + filler * 900 + "4 5 6\n")
    assert read_point_cloud(path).shape == (11, 3)
