"""Hostile mesh files: `prepare` checks a mesh's size, lines and declared counts before trimesh
reads it, names the file and the bound it breaks, and goes on with the others (the fourteenth
audit: a 45 MB ASCII PLY of four vertices and five million junk lines took 1.3 GB)."""

from __future__ import annotations

import json
import os
import struct
import zipfile
from pathlib import Path

import pytest

from pfnet.cli import main
from pfnet.data import SWEETHOME3D_PATH, prepare_dataset
from pfnet.errors import DataError
from pfnet.io.formats.meshes import MAX_EXTRA_LINES, MAX_MESH_BYTES, MAX_MESH_LINES, check_mesh_file

TETRAHEDRON_OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"


def _ply(vertices: int, fmt: str = "ascii") -> str:
    return (
        f"ply\nformat {fmt} 1.0\nelement vertex {vertices}\nproperty float x\n"
        "property float y\nproperty float z\nelement face 4\n"
        "property list uchar int vertex_indices\nend_header\n"
    )


TETRAHEDRON_PLY = _ply(4) + "0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n3 0 1 3\n3 0 2 3\n3 1 2 3\n"


def _hostile_meshes(folder: Path) -> dict[str, str]:
    """Write one file per bound into ``folder``; return ``{name: what the error says}``."""
    (folder / "tail.ply").write_text(TETRAHEDRON_PLY + "12 34 56\n" * (MAX_EXTRA_LINES + 500))
    (folder / "junk.obj").write_text(TETRAHEDRON_OBJ + "vn 0 0 1\n" * MAX_MESH_LINES)
    (folder / "longline.obj").write_text(TETRAHEDRON_OBJ[:16] + "#" * 10_000_000 + "\n")
    with open(folder / "huge.obj", "w") as fh:  # sparse: no disk taken
        fh.write(TETRAHEDRON_OBJ)
        fh.truncate(MAX_MESH_BYTES + 1)
    (folder / "forged.ply").write_text(TETRAHEDRON_PLY.replace("vertex 4", f"vertex {10**12}"))
    (folder / "forged_binary.ply").write_bytes(
        _ply(10**12, "binary_little_endian").encode() + bytes(48)
    )
    triangles = struct.pack("<12fH", *[0.0] * 12, 0) * 4
    (folder / "lying.stl").write_bytes(bytes(80) + struct.pack("<I", 10**6) + triangles)
    return {
        "tail.ply": f"{MAX_EXTRA_LINES + 500} lines after the 8 rows its header declares",
        "junk.obj": f"more than {MAX_MESH_LINES} lines",
        "longline.obj": "line 3 is longer than 65536 bytes",
        "huge.obj": f"{MAX_MESH_BYTES + 1} bytes, above the {MAX_MESH_BYTES} accepted",
        "forged.ply": "truncated PLY data: the header declares 1000000000004 rows, the body has 8",
        "forged_binary.ply": "truncated PLY data: the header declares rows of at least",
        "lying.stl": "binary STL declaring 1000000 triangles (50000084 bytes) but the file has 284",
    }


def test_each_bound_is_named_with_the_file(tmp_path: Path) -> None:
    for name, message in _hostile_meshes(tmp_path).items():
        with pytest.raises(DataError, match=f"^{tmp_path / name}: ") as caught:
            check_mesh_file(tmp_path / name)
        assert message in str(caught.value)


def test_prepare_skips_each_hostile_mesh_by_name_and_keeps_the_good_ones(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    folder = tmp_path / "src" / "c"
    folder.mkdir(parents=True)
    for index in range(3):
        (folder / f"ok{index}.obj").write_text(TETRAHEDRON_OBJ)
    (folder / "ok.ply").write_text(TETRAHEDRON_PLY + "\n")  # a blank last line is no junk
    expected = _hostile_meshes(folder)
    code = main(["prepare", str(tmp_path / "src"), "--out", str(tmp_path / "ds"), "--points", "64"])
    printed = capsys.readouterr().out
    assert code == 0
    assert f"skipped {len(expected)} files:" in printed
    for name, message in expected.items():
        assert f"{folder / name}: {message}" in printed
    manifest = json.loads((tmp_path / "ds" / "manifest.json").read_text())
    assert sum(manifest["splits"][split]["total"] for split in manifest["splits"]) == 4


def test_gltf_buffers_count_towards_the_bound(tmp_path: Path) -> None:
    with open(tmp_path / "big.bin", "wb") as fh:
        fh.truncate(MAX_MESH_BYTES)
    gltf = tmp_path / "scene.gltf"
    gltf.write_text(json.dumps({"asset": {"version": "2.0"}, "buffers": [{"uri": "big.bin"}]}))
    with pytest.raises(DataError, match=r"scene\.gltf: with its buffers \d+ bytes or more"):
        check_mesh_file(gltf)
    os.mkfifo(tmp_path / "pipe.bin")  # opening it would wait for a writer forever
    gltf.write_text(json.dumps({"asset": {"version": "2.0"}, "buffers": [{"uri": "pipe.bin"}]}))
    with pytest.raises(DataError, match=r"scene\.gltf: buffer 'pipe\.bin' is not a file beside"):
        check_mesh_file(gltf)
    glb = tmp_path / "short.glb"
    glb.write_bytes(b"glTF" + struct.pack("<III4s", 2, 10**9, 10**6, b"JSON") + b"{}")
    with pytest.raises(DataError, match=r"short\.glb: damaged GLB: it declares 1000000000 bytes"):
        check_mesh_file(glb)


@pytest.mark.slow  # end to end, or a measurement: runs in CI, not the default run
@pytest.mark.real_data
def test_the_largest_real_models_pass_the_bounds_and_prepare(tmp_path: Path) -> None:
    if not SWEETHOME3D_PATH.is_dir():
        pytest.skip(f"{SWEETHOME3D_PATH} is absent: apt-get install sweethome3d-furniture")
    models = []
    for catalogue in sorted(SWEETHOME3D_PATH.glob("*.sh3f")):
        with zipfile.ZipFile(catalogue) as archive:
            models += [
                (info.file_size, catalogue, info.filename)
                for info in archive.infolist()
                if info.filename.endswith(".obj")
            ]
    # the four largest (japaneseMaple: 8.8 MB, 283,832 lines) and the longest line (2,692 bytes)
    longest = "blendswap-cc-0/chairWithCushion/chairWithCushion.obj"
    chosen = sorted(models)[-4:] + [m for m in models if m[2] == longest]
    assert len(chosen) == 5
    for _, catalogue, member in chosen:
        folder = tmp_path / "src" / Path(member).parent.name
        folder.mkdir(parents=True)
        with zipfile.ZipFile(catalogue) as archive:
            (folder / Path(member).name).write_bytes(archive.read(member))
    report = prepare_dataset(
        tmp_path / "src", tmp_path / "ds", points=64, workers=1, progress=False
    )
    assert report.skipped == []
    assert sum(sum(counts.values()) for counts in report.counts.values()) == 5
