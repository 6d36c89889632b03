"""The tenth audit's benchmark layouts: side files (``<split>.partial.npz``,
``test.boxes.npz``) are read through the split files' checked path (a 2 MB deflated member
took 2.4 GB, an untokenizable header gave a traceback), index files are bounded before they
are read (2 GiB sparse files took 4 GB), a file listed many times is read once (20,000
repeated lines took 3.9 GB), name de-duplication is linear (20,000 shapes wanting one name
took 31 s) and an implausible name in an index is skipped and named, escaped and cut."""

from __future__ import annotations

import io
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from pfnet.data.benchmarks import load_partials
from pfnet.data.kitti import load_boxes
from pfnet.data.sources import unique_names
from pfnet.errors import DataError


def _npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.lib.format.write_array(buffer, array, allow_pickle=False)
    return buffer.getvalue()


def _raw_npy(header: str) -> bytes:
    text = header.encode("latin1")
    text += b" " * (-(len(text) + 11) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + len(text).to_bytes(2, "little") + text


def _npz(path: Path, members: dict[str, bytes], deflate: bool = False) -> Path:
    kind = zipfile.ZIP_DEFLATED if deflate else zipfile.ZIP_STORED
    with zipfile.ZipFile(path, "w", compression=kind) as archive:
        for name, data in members.items():
            archive.writestr(f"{name}.npy", data)
    return path


def test_a_deflated_partial_scan_bomb_is_refused_from_its_header(tmp_path):
    zeros = np.zeros((2_000_000, 3), np.float32)  # 24 MB deflating to about 24 KB
    offsets = np.array([0, len(zeros)], np.int64)
    _npz(
        tmp_path / "test.partial.npz",
        {"points": _npy(zeros), "offsets": _npy(offsets)},
        deflate=True,
    )
    with pytest.raises(DataError, match=r"test.partial.npz: member points.npy claims to expand"):
        load_partials(tmp_path, "test", 1)


def test_a_boxes_bomb_is_refused_before_it_is_unpacked(tmp_path):
    boxes = np.zeros((300_000, 8, 3), np.float32)
    _npz(tmp_path / "test.boxes.npz", {"boxes": _npy(boxes)}, deflate=True)
    with pytest.raises(DataError, match=r"test.boxes.npz: member boxes.npy claims to expand"):
        load_boxes(tmp_path, "test", 300_000)
    _npz(tmp_path / "test.boxes.npz", {"boxes": _npy(np.zeros((2, 8, 3), np.float32))})
    with pytest.raises(DataError, match=r"boxes must be float32 \(3, 8, 3\), got float32 \(2, 8"):
        load_boxes(tmp_path, "test", 3)


def test_a_declared_shape_is_compared_before_loading(tmp_path):
    header = "{'descr': '<f4', 'fortran_order': False, 'shape': (10, 3), }"
    _npz(
        tmp_path / "test.partial.npz",
        {"points": _raw_npy(header) + bytes(120), "offsets": _npy(np.array([0, 4], np.int64))},
    )
    with pytest.raises(DataError, match=r"test.partial.npz: points must be float32 \(4, 3\)"):
        load_partials(tmp_path, "test", 1)
    _npz(
        tmp_path / "test.partial.npz",
        {"points": _npy(np.zeros((4, 3), np.float32)), "offsets": _npy(np.zeros(5, np.int32))},
    )
    with pytest.raises(DataError, match=r"offsets must be int64 \(2,\), got int32 \(5,\)"):
        load_partials(tmp_path, "test", 1)


@pytest.mark.parametrize(
    ("file", "member", "header"),
    [
        (
            "test.partial.npz",
            "points",
            "{'descr': '<f4', 'fortran_order': False, 'shape': [(4, 3), }",
        ),
        (
            "test.partial.npz",
            "offsets",
            "{'descr': '<i8', 'fortran_order': False, 'shape': " + "(" * 200,
        ),
        (
            "test.boxes.npz",
            "boxes",
            "{'descr': '<f4', 'fortran_order': False, 'shape': [(1, 8, 3), }",
        ),
    ],
)
def test_untokenizable_side_file_headers_are_named_errors(tmp_path, file, member, header):
    arrays = (
        {"points": _npy(np.zeros((4, 3), np.float32)), "offsets": _npy(np.array([0, 4]))}
        if file == "test.partial.npz"
        else {"boxes": b""}
    )
    arrays[member] = _raw_npy(header) + bytes(96)
    _npz(tmp_path / file, arrays)
    with pytest.raises(DataError, match=rf"{file}: member {member}.npy: not a valid .npy"):
        (
            load_partials(tmp_path, "test", 1)
            if "partial" in file
            else load_boxes(tmp_path, "test", 1)
        )


def test_unique_names_is_linear_in_shapes_wanting_one_name():
    start = time.perf_counter()
    names = unique_names({f"t/c{i:05d}/m": "m" for i in range(20_000)})
    assert time.perf_counter() - start < 2  # 31 s when each search began at -2
    assert len(set(names.values())) == 20_000
    assert names["t/c00000/m"] == "m" and names["t/c00001/m"] == "m-2"
    # a name taken outright is still passed over
    assert unique_names({"a": "m", "b": "m-2", "c": "m", "d": "m"}) == {
        "a": "m",
        "b": "m-2",
        "c": "m-3",
        "d": "m-4",
    }
