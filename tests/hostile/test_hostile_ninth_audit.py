"""The ninth hostile audit's reader findings: glTF scene graphs that trimesh flattens into
gigabytes (one mesh reused by 20,000 nodes: 65 s and 5.6 GB from 1.9 MB), ``.npy`` shapes
checked only after loading (a 4 KB sparse file declaring (2, 5·10^8): 3.9 GB), ``.npy``
headers numpy cannot tokenize (a traceback that stopped a ``complete`` batch), and binary
PLY/PCD rows whose width was not bounded (500,000 rows of 8 KB: 3.9 GB of page cache).

Each hostile file is made at a size that proves its check: sparse where the size is the point.
"""

from __future__ import annotations

import json
import resource
import shutil
import struct
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from pfnet.cli import main
from pfnet.data import load_split
from pfnet.errors import DataError
from pfnet.io.clouds import read_point_cloud, write_ply
from pfnet.io.formats import MAX_BODY_BYTES
from pfnet.io.formats.meshes import (
    MAX_GLTF_DEPTH,
    MAX_GLTF_INSTANCED,
    MAX_GLTF_NODES,
    check_mesh_file,
)

TETRAHEDRON_OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"


def _glb(path: Path, nodes: list[dict], *, count: int = 12, roots: list[int] | None = None) -> Path:
    """A GLB of one tetrahedron mesh whose accessors declare ``count`` vertices and indices
    (the buffer holds 12 of each), used as the scene graph ``nodes`` says."""
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)[
        [0, 1, 2, 0, 1, 3, 0, 2, 3, 1, 2, 3]
    ]
    indices = np.arange(12, dtype=np.uint32)
    binary = vertices.tobytes() + indices.tobytes()
    document = {
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": len(binary)}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": vertices.nbytes},
            {"buffer": 0, "byteOffset": vertices.nbytes, "byteLength": indices.nbytes},
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": count, "type": "VEC3",
             "min": [0, 0, 0], "max": [1, 1, 1]},
            {"bufferView": 1, "componentType": 5125, "count": count, "type": "SCALAR"},
        ],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "nodes": nodes,
        "scenes": [{"nodes": [0] if roots is None else roots}],
        "scene": 0,
    }  # fmt: skip
    text = json.dumps(document).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<I4s", len(text), b"JSON") + text
    body += struct.pack("<I4s", len(binary), b"BIN\0") + binary
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)
    return path


def _chain(depth: int) -> list[dict]:
    return [{"mesh": 0, "children": [i + 1]} for i in range(depth - 1)] + [{"mesh": 0}]


def _hostile_scenes(folder: Path) -> dict[str, str]:
    """One GLB per bound of the scene graph; ``{name: what the error says}``."""
    many = [{"mesh": 0, "translation": [i, 0, 0]} for i in range(MAX_GLTF_NODES + 1)]
    _glb(folder / "many.glb", many, roots=list(range(len(many))))
    _glb(folder / "deep.glb", _chain(MAX_GLTF_DEPTH + 1))
    _glb(folder / "cycle.glb", [{"mesh": 0, "children": [1]}, {"mesh": 0, "children": [0]}])
    # 21 nodes share a mesh declaring a million vertices and a million indices: 42 M once
    # flattened, from a file of a few KB
    per_instance = 1_000_000
    reused = [{"mesh": 0} for _ in range(MAX_GLTF_INSTANCED // (2 * per_instance) + 1)]
    _glb(folder / "reused.glb", reused, count=per_instance, roots=list(range(len(reused))))
    # 40 levels of two edges to the same next node: 2^40 paths through 40 nodes
    diamond = [{"mesh": 0, "children": [i + 1, i + 1]} for i in range(39)] + [{"mesh": 0}]
    _glb(folder / "paths.glb", diamond)
    instanced = f"glTF scene instances its meshes to more than {MAX_GLTF_INSTANCED:,} vertices"
    return {
        "many.glb": f"glTF with {MAX_GLTF_NODES + 1} nodes; pfnet reads at most",
        "deep.glb": f"glTF nodes nested more than {MAX_GLTF_DEPTH} deep",
        "cycle.glb": "glTF node 0 is its own ancestor (a cycle)",
        "reused.glb": instanced,
        "paths.glb": instanced,
    }


def test_gltf_scene_graphs_are_bounded_before_trimesh(tmp_path: Path) -> None:
    for name, message in _hostile_scenes(tmp_path).items():
        start = time.perf_counter()
        with pytest.raises(DataError, match=f"^{tmp_path / name}: ") as caught:
            check_mesh_file(tmp_path / name)
        assert message in str(caught.value)
        assert "\n" not in str(caught.value)
        assert time.perf_counter() - start < 5, name
    # at the bounds: a chain MAX_GLTF_DEPTH deep, MAX_GLTF_NODES nodes, and the same scene
    # as a .gltf file with its buffer embedded
    check_mesh_file(_glb(tmp_path / "ok" / "deep.glb", _chain(MAX_GLTF_DEPTH)))
    nodes = [{"mesh": 0} for _ in range(MAX_GLTF_NODES)]
    check_mesh_file(_glb(tmp_path / "ok" / "many.glb", nodes, roots=list(range(len(nodes)))))
    gltf = tmp_path / "deep.gltf"
    chain = _chain(MAX_GLTF_DEPTH + 1)
    gltf.write_text(json.dumps({"asset": {"version": "2.0"}, "nodes": chain, "meshes": []}))
    with pytest.raises(DataError, match=r"deep\.gltf: glTF nodes nested more than 64 deep"):
        check_mesh_file(gltf)


def test_prepare_skips_hostile_scenes_by_name_and_reads_a_good_glb(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    folder = tmp_path / "src" / "chair"
    folder.mkdir(parents=True)
    for index in range(2):
        (folder / f"ok{index}.obj").write_text(TETRAHEDRON_OBJ)
    _glb(folder / "ok.glb", [{"mesh": 0, "children": [1]}, {"mesh": 0}])
    expected = _hostile_scenes(folder)
    code = main(["prepare", str(tmp_path / "src"), "--out", str(tmp_path / "ds"), "--points", "64"])
    printed = capsys.readouterr().out
    assert code == 0
    assert f"skipped {len(expected)} files:" in printed
    for name, message in expected.items():
        assert f"{folder / name}: {message}" in printed
    manifest = json.loads((tmp_path / "ds" / "manifest.json").read_text())
    assert sum(manifest["splits"][split]["total"] for split in manifest["splits"]) == 3


def _sparse_npy(path: Path, shape: tuple[int, ...], descr: str = "<f4") -> Path:
    """A ``.npy`` of ``shape`` whose data is a hole: 4 KB on disk whatever it declares."""
    header = f"{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}"
    header += " " * (-(10 + len(header) + 1) % 64) + "\n"
    with open(path, "wb") as fh:
        fh.write(b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header.encode())
        fh.truncate(fh.tell() + int(np.prod(shape)) * np.dtype(descr).itemsize)
    return path


@pytest.mark.parametrize(
    ("shape", "descr", "message"),
    [
        ((2, 500_000_000), "<f4", "500000000 columns of 2 rows"),  # 2 GB apparent
        ((1, 150_000_000, 3), "<f4", "expected an (N, 3) array of points, got shape"),
        ((100_000_000,), "<f8", "expected an (N, 3) array of points, got shape"),
        ((100_000_000, 3), "|b1", "expected numeric coordinates, got dtype bool"),
        ((10, 3), "<c8", "expected real coordinates"),
    ],
)
def test_npy_shapes_and_dtypes_are_refused_from_the_header(
    tmp_path: Path, shape: tuple[int, ...], descr: str, message: str
) -> None:
    file = _sparse_npy(tmp_path / "cloud.npy", shape, descr)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    start = time.perf_counter()
    with pytest.raises(DataError, match=f"^{file}: ") as caught:
        read_point_cloud(file)
    assert message in str(caught.value)
    assert time.perf_counter() - start < 2
    # the peak resident size (KB) grew by far less than the array
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 200_000


def test_npy_columns_beyond_xyz_are_not_copied(tmp_path: Path) -> None:
    cloud = np.random.default_rng(0).normal(size=(1000, 7))
    np.save(tmp_path / "wide.npy", cloud)
    np.save(tmp_path / "fortran.npy", np.asfortranarray(cloud))
    for name in ("wide.npy", "fortran.npy"):
        np.testing.assert_allclose(read_point_cloud(tmp_path / name), cloud[:, :3], rtol=1e-6)


def _mutated_headers() -> list[bytes]:
    """A valid 300-point ``.npy`` with each byte of its header replaced in turn by a bracket,
    a quote or another character numpy's header tokenizer trips on."""
    buffer = __import__("io").BytesIO()
    np.save(buffer, np.random.default_rng(0).normal(size=(300, 3)).astype(np.float32))
    data = buffer.getvalue()
    end = 10 + struct.unpack("<H", data[8:10])[0]
    files = []
    for position in range(10, end - 1):
        for char in b"[({'\"\\#}),\x00\xff":
            if data[position] != char:
                files.append(data[:position] + bytes([char]) + data[position + 1 :])
    return files


def test_npy_headers_numpy_cannot_tokenize_are_named(tmp_path: Path) -> None:
    tok = tmp_path / "tok.npy"
    refused = 0
    for mutated in _mutated_headers():
        tok.write_bytes(mutated)
        try:
            points = read_point_cloud(tok)
        except DataError as err:
            assert str(err).startswith(f"{tok}: ") and "\n" not in str(err), err
            refused += 1
        else:
            assert points.shape == (300, 3) and points.dtype == np.float32
    assert refused > 100
    # the audit's case: a stray "[" left unclosed (numpy raises tokenize.TokenError)
    tok.write_bytes(_stray_bracket())
    with pytest.raises(DataError, match=f"^{tok}: not a valid .npy array file"):
        read_point_cloud(tok)


def _stray_bracket() -> bytes:
    buffer = __import__("io").BytesIO()
    np.save(buffer, np.zeros((300, 3), np.float32))
    data = buffer.getvalue()
    return data.replace(b"'shape': (300, 3), }", b"'shape': [(300, 3), }", 1).replace(
        b"  \n", b" \n", 1
    )


def test_a_split_member_numpy_cannot_tokenize_is_named(tmp_path: Path, tiny_dataset: Path) -> None:
    data = shutil.copytree(tiny_dataset, tmp_path / "data")
    with zipfile.ZipFile(tiny_dataset / "test.npz") as archive:
        members = {info.filename: archive.read(info) for info in archive.infolist()}
    points = members["points.npy"]
    members["points.npy"] = points.replace(b"'shape': (", b"'shape': ((", 1).replace(
        b"  \n", b" \n", 1
    )
    assert len(members["points.npy"]) == len(points)
    with zipfile.ZipFile(data / "test.npz", "w") as archive:
        for name, content in members.items():
            archive.writestr(name, content)
    with pytest.raises(DataError, match="member points.npy: not a valid .npy array file"):
        load_split(data, "test")


def _wide_ply(path: Path, rows: int, extra: int) -> Path:
    """A sparse binary PLY of ``rows`` rows of x y z and ``extra`` doubles each."""
    props = "".join(f"property double a{i}\n" for i in range(extra))
    header = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {rows}\nproperty float x\n"
        f"property float y\nproperty float z\n{props}end_header\n"
    )
    with open(path, "wb") as fh:
        fh.write(header.encode())
        fh.truncate(fh.tell() + rows * (12 + 8 * extra))
    return path


def _wide_pcd(path: Path, points: int, extra: int) -> Path:
    header = (
        f"VERSION .7\nFIELDS x y z a\nSIZE 4 4 4 8\nTYPE F F F F\nCOUNT 1 1 1 {extra}\n"
        f"WIDTH {points}\nHEIGHT 1\nPOINTS {points}\nDATA binary\n"
    )
    with open(path, "wb") as fh:
        fh.write(header.encode())
        fh.truncate(fh.tell() + points * (12 + 8 * extra))
    return path


def test_wide_binary_rows_are_bounded_by_the_bytes_they_span(tmp_path: Path) -> None:
    rows = MAX_BODY_BYTES // 8012 + 1  # rows of 8,012 bytes: just over the bound
    for file in (
        _wide_ply(tmp_path / "wide.ply", rows, 1000),
        _wide_pcd(tmp_path / "wide.pcd", rows, 1000),
    ):
        start = time.perf_counter()
        with pytest.raises(DataError, match=f"^{file}: .* span {rows * 8012} bytes; pfnet reads"):
            read_point_cloud(file)
        assert time.perf_counter() - start < 2
    # the same rows, fewer of them, are read
    assert read_point_cloud(_wide_ply(tmp_path / "ok.ply", 1000, 1000)).shape == (1000, 3)
    assert read_point_cloud(_wide_pcd(tmp_path / "ok.pcd", 1000, 1000)).shape == (1000, 3)


def test_a_complete_batch_names_each_hostile_file_and_completes_the_good_one(
    tmp_path: Path, capsys
) -> None:
    torch = pytest.importorskip("torch")
    from pfnet.inference.checkpoint import save_checkpoint
    from pfnet.models import build_model
    from pfnet.training.config import preset_config

    config = preset_config("small").replace(n_points=512, width=0.125)
    checkpoint = tmp_path / "m.pt"
    torch.manual_seed(0)
    save_checkpoint(
        checkpoint, {"config": config.to_dict(), "model": build_model(config).state_dict()}
    )
    good = tmp_path / "good.ply"
    write_ply(good, np.random.default_rng(0).normal(size=(400, 3)).astype(np.float32))
    (tmp_path / "tok.npy").write_bytes(_stray_bracket())
    bad = [
        tmp_path / "tok.npy",
        _sparse_npy(tmp_path / "wide2.npy", (2, 500_000_000)),
        _wide_ply(tmp_path / "wideply.ply", MAX_BODY_BYTES // 8012 + 1, 1000),
    ]
    out = tmp_path / "out"
    args = ["complete", *map(str, bad), str(good), "--out", str(out)]
    assert main([*args, "--checkpoint", str(checkpoint), "--device", "cpu"]) == 2
    captured = capsys.readouterr()
    assert "completed 1 of 4" in captured.out
    assert "Traceback" not in captured.err
    for file in bad:
        assert str(file) in captured.err
    assert sorted(p.name for p in out.iterdir()) == ["good_completed.ply", "good_missing.ply"]
