"""Tests for pfnet.io.clouds: every reader against hand-written files, round trips, bad files."""

from __future__ import annotations

import os
import struct

import numpy as np
import pytest

from pfnet.errors import DataError
from pfnet.io.clouds import read_point_cloud, save_npy, write_ply
from pfnet.io.files import atomic_path


@pytest.fixture
def cloud() -> np.ndarray:
    """A small float32 cloud whose values are exact in float32 and in short decimal text."""
    rng = np.random.default_rng(0)
    return (rng.integers(-4000, 4000, size=(37, 3)) / 1024.0).astype(np.float32)


def _ply_header(fmt: str, n: int, vertex_props: list[str], extra: list[str] = ()) -> bytes:
    lines = ["ply", f"format {fmt} 1.0", "comment test file", f"element vertex {n}"]
    lines += [f"property {p}" for p in vertex_props]
    lines += list(extra)
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


# ----------------------------------------------------------------------------- round trips


def test_write_ply_round_trip(tmp_path, cloud):
    path = tmp_path / "c.ply"
    write_ply(path, cloud)
    out = read_point_cloud(path)
    assert out.dtype == np.float32 and out.shape == cloud.shape
    np.testing.assert_array_equal(out, cloud)


def test_write_ply_with_colors_round_trip(tmp_path, cloud):
    path = tmp_path / "c.ply"
    colors = np.tile(np.array([[1.0, 0.5, 0.0]]), (len(cloud), 1))
    write_ply(path, cloud, colors=colors)
    np.testing.assert_array_equal(read_point_cloud(path), cloud)
    data = path.read_bytes()
    header, body = data.split(b"end_header\n")
    assert b"property uchar red" in header
    rows = np.frombuffer(body, dtype=[("xyz", "<f4", 3), ("rgb", "u1", 3)])
    np.testing.assert_array_equal(rows["rgb"][0], [255, 128, 0])


def test_write_ply_is_readable_by_trimesh(tmp_path, cloud):
    trimesh = pytest.importorskip("trimesh")
    path = tmp_path / "c.ply"
    write_ply(path, cloud, colors=np.zeros((len(cloud), 3), dtype=np.uint8))
    loaded = trimesh.load(path)
    np.testing.assert_array_equal(np.asarray(loaded.vertices, dtype=np.float32), cloud)


@pytest.mark.parametrize("encoding", ["binary", "ascii"])
def test_reads_trimesh_mesh_ply_ignoring_faces(tmp_path, encoding):
    trimesh = pytest.importorskip("trimesh")
    mesh = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    path = tmp_path / "box.ply"
    path.write_bytes(mesh.export(file_type="ply", encoding=encoding))
    out = read_point_cloud(path)
    np.testing.assert_allclose(out, mesh.vertices.astype(np.float32), rtol=0, atol=1e-6)


def test_save_npy_round_trip(tmp_path, cloud):
    path = tmp_path / "c.npy"
    save_npy(path, cloud)
    np.testing.assert_array_equal(read_point_cloud(path), cloud)
    assert [p.name for p in tmp_path.iterdir()] == ["c.npy"]


def test_npy_any_numeric_dtype_and_extra_columns(tmp_path, cloud):
    path = tmp_path / "c.npy"
    np.save(path, np.concatenate([cloud.astype(np.float64), np.ones((len(cloud), 3))], axis=1))
    np.testing.assert_array_equal(read_point_cloud(path), cloud)
    np.save(path, np.arange(12, dtype=np.int16).reshape(4, 3))
    np.testing.assert_array_equal(read_point_cloud(path), np.arange(12).reshape(4, 3))


@pytest.mark.parametrize(
    ("fmt", "endian"), [("binary_little_endian", "<"), ("binary_big_endian", ">")]
)
@pytest.mark.parametrize("ctype", ["f4", "f8", "i2", "i4", "u1"])
def test_binary_ply_types_and_endianness(tmp_path, fmt, endian, ctype):
    names = {"f4": "float", "f8": "double", "i2": "short", "i4": "int", "u1": "uchar"}
    pts = np.arange(30).reshape(10, 3) % 200
    dtype = np.dtype([("nx", endian + "f4"), ("x", endian + ctype), ("y", endian + ctype)])
    dtype = np.dtype(dtype.descr + [("z", endian + ctype), ("red", "u1")])
    rows = np.zeros(len(pts), dtype=dtype)
    rows["x"], rows["y"], rows["z"], rows["nx"] = pts[:, 0], pts[:, 1], pts[:, 2], 7.0
    props = ["float nx", f"{names[ctype]} x", f"{names[ctype]} y", f"{names[ctype]} z"]
    face = np.array([(3, (0, 1, 2))], dtype=[("n", "u1"), ("v", endian + "i4", 3)])
    header = _ply_header(
        fmt,
        len(pts),
        props + ["uchar red"],
        ["element face 1", "property list uchar int vertex_indices"],
    )
    path = tmp_path / "t.ply"
    path.write_bytes(header + rows.tobytes() + face.tobytes())
    np.testing.assert_array_equal(read_point_cloud(path), pts.astype(np.float32))


def test_binary_ply_element_with_lists_before_vertex(tmp_path):
    pts = np.array([[1.5, 2.0, -3.0], [4.0, 5.0, 6.25]], dtype="<f4")
    header = (
        b"ply\nformat binary_little_endian 1.0\n"
        b"element material 2\nproperty list uchar ushort ids\nproperty float shine\n"
        b"element vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
        b"property list uchar float weights\nend_header\n"
    )
    material = struct.pack("<BHHf", 2, 1, 2, 0.5) + struct.pack("<Bf", 0, 0.25)
    vertices = b"".join(struct.pack("<fffBf", *p, 1, 9.0) for p in pts)
    path = tmp_path / "l.ply"
    path.write_bytes(header + material + vertices)
    np.testing.assert_array_equal(read_point_cloud(path), pts)


def test_ascii_ply_with_faces_and_reordered_properties(tmp_path):
    text = (
        "ply\nformat ascii 1.0\ncomment made by hand\n"
        "element vertex 3\nproperty uchar red\nproperty double z\nproperty double x\n"
        "property double y\nelement face 1\nproperty list uchar int vertex_indices\n"
        "end_header\n"
        "255 3 1 2\n0 6 4 5\n\n10 9.5 7 8\n3 0 1 2\n"
    )
    path = tmp_path / "a.ply"
    path.write_text(text)
    np.testing.assert_array_equal(
        read_point_cloud(path), np.array([[1, 2, 3], [4, 5, 6], [7, 8, 9.5]], np.float32)
    )


def test_ascii_ply_list_in_vertex_and_element_before(tmp_path):
    text = (
        "ply\nformat ascii 1.0\nelement camera 1\nproperty float f\n"
        "element vertex 2\nproperty float x\nproperty list uchar int tags\n"
        "property float y\nproperty float z\nend_header\n"
        "35.0\n1 2 7 7 2 3\n4 0 5 6\n"
    )
    path = tmp_path / "a.ply"
    path.write_text(text)
    np.testing.assert_array_equal(read_point_cloud(path), [[1, 2, 3], [4, 5, 6]])


@pytest.mark.parametrize("suffix", [".xyz", ".pts", ".txt"])
@pytest.mark.parametrize("sep", [" ", "\t", ",", ", "])
def test_text_round_trip(tmp_path, cloud, suffix, sep):
    path = tmp_path / f"c{suffix}"
    lines = [sep.join(f"{v!r}" for v in map(float, p)) + f"{sep}0.5{sep}1" for p in cloud]
    path.write_text("\n".join(lines) + "\n")
    np.testing.assert_array_equal(read_point_cloud(path), cloud)


def test_text_comments_count_header_and_column_names(tmp_path):
    path = tmp_path / "c.pts"
    path.write_text("2\n1 2 3 100 20 30\n# comment\n\n4 5 6 9 9 9\n")
    np.testing.assert_array_equal(read_point_cloud(path), [[1, 2, 3], [4, 5, 6]])
    path = tmp_path / "c.txt"
    path.write_text("// exported\nx,y,z\n1,2,3\n4,5,6,7\n")
    np.testing.assert_array_equal(read_point_cloud(path), [[1, 2, 3], [4, 5, 6]])


def _pcd(fields: str, size: str, typ: str, count: str, n: int, data: str) -> bytes:
    return (
        f"# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {fields}\n"
        f"SIZE {size}\nTYPE {typ}\nCOUNT {count}\nWIDTH {n}\nHEIGHT 1\n"
        f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n"
    ).encode("ascii")


def test_pcd_ascii(tmp_path, cloud):
    body = "\n".join(f"{x!r} {y!r} {z!r} 4.2e+06" for x, y, z in cloud.tolist())
    path = tmp_path / "c.pcd"
    path.write_bytes(_pcd("x y z rgb", "4 4 4 4", "F F F F", "1 1 1 1", len(cloud), "ascii"))
    with open(path, "ab") as fh:
        fh.write(body.encode() + b"\n")
    np.testing.assert_array_equal(read_point_cloud(path), cloud)


def test_pcd_binary_with_multi_count_field_and_nan_points(tmp_path, cloud):
    rows = np.zeros(len(cloud), dtype=[("n", "<f4", 2), ("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
    rows["x"], rows["y"], rows["z"] = cloud[:, 0], cloud[:, 1], cloud[:, 2]
    rows["x"][5] = np.nan  # an invalid point of an organised cloud
    path = tmp_path / "c.pcd"
    head = _pcd("normal x y z", "4 8 8 8", "F F F F", "2 1 1 1", len(cloud), "binary")
    path.write_bytes(head + rows.tobytes())
    np.testing.assert_array_equal(read_point_cloud(path), np.delete(cloud, 5, axis=0))


def _lzf_literals(data: bytes) -> bytes:
    """A valid LZF stream made only of literal runs (at most 32 bytes each)."""
    out = bytearray()
    for i in range(0, len(data), 32):
        chunk = data[i : i + 32]
        out.append(len(chunk) - 1)
        out += chunk
    return bytes(out)


def test_pcd_binary_compressed(tmp_path, cloud):
    columns = cloud.T.astype("<f4").tobytes() + np.full(len(cloud), 3, "<u2").tobytes()
    payload = _lzf_literals(columns)
    head = _pcd("x y z label", "4 4 4 2", "F F F U", "1 1 1 1", len(cloud), "binary_compressed")
    path = tmp_path / "c.pcd"
    path.write_bytes(head + struct.pack("<II", len(payload), len(columns)) + payload)
    np.testing.assert_array_equal(read_point_cloud(path), cloud)


def test_pcd_binary_compressed_back_reference(tmp_path):
    # Two equal points stored column by column: x x y y z z. Each column is a 4-byte
    # literal (ctrl 3) followed by a back reference of length 4 (ctrl (4 - 2) << 5) at
    # distance 4 (offset byte 3, since liblzf stores distance - 1).
    payload = b""
    for value in (1.0, -2.0, 0.5):
        payload += bytes([3]) + struct.pack("<f", value) + bytes([2 << 5, 3])
    head = _pcd("x y z", "4 4 4", "F F F", "1 1 1", 2, "binary_compressed")
    path = tmp_path / "c.pcd"
    path.write_bytes(head + struct.pack("<II", len(payload), 24) + payload)
    np.testing.assert_array_equal(read_point_cloud(path), [[1, -2, 0.5], [1, -2, 0.5]])


def test_pcd_binary_compressed_long_back_reference(tmp_path):
    # A run of 40 zero bytes: literal 1 byte, then ctrl 7 << 5 with an extra length byte
    # (7 + 30 + 2 = 39 bytes copied from distance 1).
    payload = bytes([0, 0, 7 << 5, 30, 0])
    head = _pcd("x y z", "4 4 4", "F F F", "1 1 1", 3, "binary_compressed")
    path = tmp_path / "z.pcd"
    path.write_bytes(head + struct.pack("<II", len(payload), 36) + payload)
    with pytest.raises(DataError, match=r"z\.pcd: corrupt .*: expands beyond the declared 36"):
        read_point_cloud(path)
    payload = bytes([0, 0, 7 << 5, 26, 0])  # 1 + 35 = 36 bytes
    path.write_bytes(head + struct.pack("<II", len(payload), 36) + payload)
    np.testing.assert_array_equal(read_point_cloud(path), np.zeros((3, 3)))


# --------------------------------------------------------------------------- atomic writes


def test_atomic_path_replaces_on_success_and_keeps_suffix(tmp_path):
    target = tmp_path / "out.png"
    target.write_text("old")
    with atomic_path(target) as tmp:
        assert tmp.parent == tmp_path and tmp.suffix == ".png" and tmp != target
        tmp.write_text("new")
        assert target.read_text() == "old"
    assert target.read_text() == "new"
    assert [p.name for p in tmp_path.iterdir()] == ["out.png"]


def test_atomic_path_removes_temp_and_keeps_old_file_on_error(tmp_path):
    target = tmp_path / "out.ply"
    target.write_text("old")
    with pytest.raises(RuntimeError, match="boom"):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.ply"]


def test_write_ply_bad_input_leaves_nothing(tmp_path, cloud):
    with pytest.raises(DataError, match=r"shape \(N, 3\)"):
        write_ply(tmp_path / "a.ply", cloud[:, :2])
    bad = cloud.copy()
    bad[0, 0] = np.nan
    with pytest.raises(DataError, match="finite"):
        write_ply(tmp_path / "a.ply", bad)
    with pytest.raises(DataError, match="colors must have shape"):
        write_ply(tmp_path / "a.ply", cloud, colors=np.zeros((3, 3)))
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------ bad files


def test_missing_file_directory_and_unknown_suffix(tmp_path):
    with pytest.raises(DataError, match=r"nope\.ply: no such file"):
        read_point_cloud(tmp_path / "nope.ply")
    (tmp_path / "dir.npy").mkdir()
    with pytest.raises(DataError, match=r"dir\.npy: a folder, not a point cloud file"):
        read_point_cloud(tmp_path / "dir.npy")
    (tmp_path / "a.obj").write_text("v 1 2 3\n")
    with pytest.raises(DataError, match=r"a\.obj: unsupported point cloud suffix '\.obj'"):
        read_point_cloud(tmp_path / "a.obj")


@pytest.mark.parametrize("suffix", [".npy", ".ply", ".xyz", ".pts", ".txt", ".pcd"])
def test_empty_file(tmp_path, suffix):
    path = tmp_path / f"empty{suffix}"
    path.write_bytes(b"")
    with pytest.raises(DataError, match=rf"empty\{suffix}: "):
        read_point_cloud(path)


@pytest.mark.parametrize(
    ("array", "message"),
    [
        (np.zeros((0, 3), np.float32), "holds no points"),
        (np.zeros(3, np.float32), r"expected an \(N, 3\) array of points, got shape \(3,\)"),
        (np.zeros((5, 2)), r"got shape \(5, 2\)"),
        (np.zeros((2, 5, 3)), r"got shape \(2, 5, 3\)"),
        (np.array([["a", "b", "c"]]), "expected numeric coordinates"),
        (np.ones((2, 3), dtype=bool), "expected numeric coordinates"),
        (np.ones((2, 3), dtype=complex), "expected real coordinates"),
        (np.array([[0, 0, np.nan], [1, 1, 1]]), r"1 point\(s\) have NaN or infinite"),
        (np.array([[0, 0, np.inf], [1, -np.inf, 1]]), r"2 point\(s\) have NaN or infinite"),
    ],
)
def test_bad_npy(tmp_path, array, message):
    path = tmp_path / "bad.npy"
    np.save(path, array)
    with pytest.raises(DataError, match=rf"bad\.npy: .*{message}"):
        read_point_cloud(path)


def test_npy_pickled_object_and_garbage(tmp_path):
    path = tmp_path / "obj.npy"
    np.save(path, np.array([object()], dtype=object), allow_pickle=True)
    with pytest.raises(DataError, match=r"obj\.npy: not a valid \.npy array file"):
        read_point_cloud(path)
    path = tmp_path / "junk.npy"
    path.write_bytes(b"this is not numpy data at all")
    with pytest.raises(DataError, match=r"junk\.npy: not a valid \.npy array file"):
        read_point_cloud(path)
    path = tmp_path / "cut.npy"
    np.save(path, np.ones((100, 3)))
    path.write_bytes(path.read_bytes()[:200])
    with pytest.raises(DataError, match=r"cut\.npy: the \.npy header declares shape \(100, 3\)"):
        read_point_cloud(path)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("1 2 3\n4 5\n", "line 2 has 2 column"),
        ("1 2 3\n4 five 6\n", "line 2 is not numeric: '4 five 6'"),
        ("# only a comment\n\n", "holds no points"),
        ("x y z\n", "holds no points"),
        ("1 2 3\nnan 0 0\n", r"1 point\(s\) have NaN or infinite"),
        ("1 2\n", "line 1 has 2 column"),
    ],
)
def test_bad_text(tmp_path, text, message):
    path = tmp_path / "bad.xyz"
    path.write_text(text)
    with pytest.raises(DataError, match=rf"bad\.xyz: .*{message}"):
        read_point_cloud(path)


def test_text_not_utf8(tmp_path):
    path = tmp_path / "bin.txt"
    path.write_bytes(b"\xff\xfe\x00\x81 binary")
    with pytest.raises(DataError, match=r"bin\.txt: not a text file"):
        read_point_cloud(path)


_GOOD_PROPS = ["float x", "float y", "float z"]


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"plx\nformat ascii 1.0\nend_header\n", "not a PLY file"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\n", "truncated header"),
        (b"ply\nelement vertex 1\nproperty float x\nend_header\n1\n", "no format line"),
        (b"ply\nformat binary_middle_endian 1.0\nend_header\n", "unsupported PLY format"),
        (b"ply\nformat ascii 1.0\nelement face 0\nend_header\n", "no vertex element"),
        (b"ply\nformat ascii 1.0\nelement vertex x\nend_header\n", "malformed PLY element"),
        (b"ply\nformat ascii 1.0\nproperty float x\nend_header\n", "property before any"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty x\nend_header\n", "malformed PLY pr"),
        (b"ply\nformat ascii 1.0\nbogus line\nend_header\n", "unexpected PLY header line"),
        (
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
            b"end_header\n1 2\n",
            "no 'z' property",
        ),
        (
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float128 x\nend_header\n",
            "unknown PLY property type 'float128'",
        ),
        (
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty list uchar float x\n"
            b"property float y\nproperty float z\nend_header\n1 1 2 3\n",
            "vertex property 'x' is a list",
        ),
        (_ply_header("ascii", 3, _GOOD_PROPS) + b"1 2 3\n4 5 6\n", "truncated PLY data"),
        (_ply_header("ascii", 2, _GOOD_PROPS) + b"1 2 3\n4 5 y\n", "malformed PLY vertex data"),
        (_ply_header("ascii", 2, _GOOD_PROPS) + b"1 2 3\n4 5\n", "malformed PLY vertex data"),
        (_ply_header("ascii", 0, _GOOD_PROPS), "holds no points"),
        (_ply_header("ascii", 1, _GOOD_PROPS) + b"1 nan 3\n", "NaN or infinite"),
        (
            _ply_header("binary_little_endian", 3, _GOOD_PROPS) + b"\0" * 30,
            "truncated PLY data: element 'vertex' needs 36 bytes, 30 left",
        ),
        (
            _ply_header("binary_big_endian", 2, [*_GOOD_PROPS, "list uchar int ids"]) + b"\0" * 13,
            "element 'vertex' declares 2 rows of at least 13 bytes, 13 bytes left",
        ),
    ],
)
def test_bad_ply(tmp_path, data, message):
    path = tmp_path / "bad.ply"
    path.write_bytes(data)
    with pytest.raises(DataError, match=rf"bad\.ply: .*{message}"):
        read_point_cloud(path)


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\n", "truncated header"),
        (b"FIELDS x y z\nTYPE F F F\nPOINTS 1\nDATA ascii\n1 2 3\n", "no SIZE line"),
        (_pcd("x y", "4 4", "F F", "1 1", 1, "ascii") + b"1 2\n", "no 'z' field"),
        (_pcd("x y z", "4 4", "F F F", "1 1 1", 1, "ascii") + b"1 2 3\n", "differ in length"),
        (_pcd("x y z", "4 4 2", "F F F", "1 1 1", 1, "ascii") + b"1 2 3\n", "unsupported PCD"),
        (_pcd("x y z", "4 4 4", "F F F", "1 1 1", 1, "lzma") + b"1 2 3\n", "DATA mode 'lzma'"),
        (_pcd("x y z", "4 4 4", "F F F", "1 1 1", 2, "ascii") + b"1 2 3\n", "truncated PCD"),
        (_pcd("x y z", "4 4 4", "F F F", "1 1 1", 1, "ascii") + b"1 2 c\n", "malformed PCD"),
        (_pcd("x y z", "4 4 4", "F F F", "1 1 1", 1, "ascii") + b"1 2\n", "fewer values"),
        (_pcd("x y z", "4 4 4", "F F F", "1 1 1", 0, "ascii"), "holds no points"),
        (_pcd("x y z", "4 4 4", "F F F", "1 1 1", 2, "binary") + b"\0" * 20, "truncated PCD"),
        (
            _pcd("x y z", "4 4 4", "F F F", "1 1 1", 1, "binary_compressed") + b"\1\0",
            "truncated PCD binary_compressed",
        ),
        (
            _pcd("x y z", "4 4 4", "F F F", "1 1 1", 1, "binary_compressed")
            + struct.pack("<II", 3, 12)
            + bytes([2 << 5, 9, 0]),
            "corrupt PCD binary_compressed",
        ),
        (
            _pcd("x y z", "4 4 4", "F F F", "1 1 1", 1, "binary_compressed")
            + struct.pack("<II", 5, 4)
            + bytes([3, 0, 0, 0, 0]),
            "declares 4 bytes, the header's 1 points need 12",
        ),
        (
            b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS many\nDATA ascii\n",
            "malformed SIZE/COUNT/POINTS",
        ),
    ],
)
def test_bad_pcd(tmp_path, data, message):
    path = tmp_path / "bad.pcd"
    path.write_bytes(data)
    with pytest.raises(DataError, match=rf"bad\.pcd: .*{message}"):
        read_point_cloud(path)


def test_os_error_is_reported_as_data_error(tmp_path, monkeypatch):
    path = tmp_path / "locked.npy"
    np.save(path, np.ones((2, 3)))

    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(os, "preadv", refuse)  # how every binary body is read
    with pytest.raises(DataError, match=r"locked\.npy: cannot read: Permission denied"):
        read_point_cloud(path)
