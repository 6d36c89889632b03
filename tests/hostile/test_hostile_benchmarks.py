"""The tenth audit's benchmark layouts: side files (``<split>.partial.npz``,
``test.boxes.npz``) are read through the split files' checked path (a 2 MB deflated member
took 2.4 GB, an untokenizable header gave a traceback), index files are bounded before they
are read (2 GiB sparse files took 4 GB), a file listed many times is read once (20,000
repeated lines took 3.9 GB), name de-duplication is linear (20,000 shapes wanting one name
took 31 s) and an implausible name in an index is skipped and named, escaped and cut."""

from __future__ import annotations

import io
import json
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
from brute import write_pcd

from pfnet.data.benchmarks import load_partials, prepare_benchmark
from pfnet.data.kitti import load_boxes
from pfnet.data.layouts import MAX_INDEX_BYTES
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


def _shapenet_tree(root: Path, lines: list[str]) -> Path:
    rng = np.random.default_rng(0)
    (root / "shapenet_pc").mkdir(parents=True)
    for stem in ("02690-mod1", "02690-mod2"):
        np.save(root / "shapenet_pc" / f"{stem}.npy", rng.normal(size=(8192, 3)).astype("f4"))
    (root / "ShapeNet-55").mkdir()
    (root / "ShapeNet-55" / "train.txt").write_text("\n".join(lines) + "\n")
    return root


def test_index_files_are_bounded_before_they_are_read(tmp_path):
    root = _shapenet_tree(tmp_path / "sn", ["02690-mod1.npy"])
    with open(root / "ShapeNet-55" / "train.txt", "r+b") as fh:
        fh.truncate(2 << 30)  # sparse: 2 GiB of NULs after the line
    with pytest.raises(DataError, match=r"train.txt: larger than 16 MB; not a split list"):
        prepare_benchmark(root, tmp_path / "out", "shapenet-55")
    pcn = tmp_path / "pcn"
    (pcn / "test" / "complete").mkdir(parents=True)
    (pcn / "PCN.json").write_bytes(b"[]")
    with open(pcn / "PCN.json", "r+b") as fh:
        fh.truncate(MAX_INDEX_BYTES + 1)
    with pytest.raises(DataError, match=r"PCN.json: larger than 16 MB; not a category file"):
        prepare_benchmark(pcn, tmp_path / "out", "pcn")


def test_repeated_entries_are_read_once_and_named(tmp_path):
    lines = ["02690-mod1.npy", *["02690-mod2.npy"] * 20_000]
    root = _shapenet_tree(tmp_path / "sn", lines)
    report = prepare_benchmark(root, tmp_path / "out", "shapenet-55")
    assert report.counts["train"] == {"02690": 2}
    assert any(
        path.endswith("02690-mod2.npy") and "listed 20000 times in ShapeNet-55/train.txt" in why
        for path, why in report.skipped
    )


def test_implausible_names_are_skipped_escaped_and_cut(tmp_path):
    lines = ["02690-mod1.npy", "02690-" + "m" * 300 + ".npy", "\x1b[31mRED\x1b[0m-evil.npy"]
    root = _shapenet_tree(tmp_path / "sn", lines)
    report = prepare_benchmark(root, tmp_path / "out", "shapenet-55")
    assert report.counts["train"] == {"02690": 1}
    text = report.summary()
    assert "\x1b" not in text and "\\x1b[31mRED" in text
    long = [path for path, _ in report.skipped if "mmm" in path]
    assert len(long) == 1 and len(long[0]) < len(str(root)) + 150 and long[0].endswith("...")
    # PCN.json: a model name over 255 bytes no longer aborts the run
    pcn = tmp_path / "pcn"
    points = np.random.default_rng(1).normal(size=(16384, 3)).astype(np.float32)
    write_pcd(pcn / "test" / "complete" / "t" / "m.pcd", points)
    write_pcd(pcn / "test" / "partial" / "t" / "m" / "00.pcd", points[:100])
    record = {"taxonomy_id": "t", "taxonomy_name": "c", "test": ["m", "m" * 300]}
    (pcn / "PCN.json").write_text(json.dumps([record]))
    report = prepare_benchmark(pcn, tmp_path / "out-pcn", "pcn")
    assert report.counts["test"] == {"c": 1}
    [(where, why)] = report.skipped
    assert where.endswith("m" * 100 + "...") and "longer than 200" in why
