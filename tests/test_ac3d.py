"""The AC3D reader (``pfnet.io.formats.ac3d``) on forged ``.ac``/``.acc`` files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pfnet.errors import DataError
from pfnet.io.formats.ac3d import parse_ac3d, read_ac3d

HEADER = 'AC3Db\nMATERIAL "m" rgb 1 1 1 amb 1 1 1 emis 0 0 0 spec 0 0 0 shi 1 trans 0\n'

QUAD = """OBJECT poly
name "quad"
{extra}numvert 4
0 0 0
1 0 0
1 1 0
0 1 0
numsurf 1
SURF 0x10
mat 0
refs 4
0 0 0
1 1 0
2 1 1
3 0 1
kids {kids}
"""


def _quad(extra: str = "", kids: int = 0) -> str:
    return QUAD.format(extra=extra, kids=kids)


def _world(*objects: str, kids: int | None = None) -> bytes:
    n = len(objects) if kids is None else kids
    return (HEADER + f"OBJECT world\nkids {n}\n" + "".join(objects)).encode()


def _area(mesh) -> float:
    v = mesh.vertices[mesh.faces]
    return float(0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1).sum())


def test_a_quad_is_two_triangles() -> None:
    mesh = parse_ac3d(_world(_quad()))
    assert mesh.vertices.shape == (4, 3) and mesh.faces.tolist() == [[0, 1, 2], [0, 2, 3]]
    assert _area(mesh) == pytest.approx(1.0) and mesh.objects == 2


def test_a_pentagon_is_fanned_from_its_first_vertex() -> None:
    ring = "\n".join(f"{np.cos(a):.6f} {np.sin(a):.6f} 0" for a in np.arange(5) * 2 * np.pi / 5)
    text = (
        f"OBJECT poly\nnumvert 5\n{ring}\nnumsurf 1\nSURF 0x0\nmat 0\nrefs 5\n"
        + "".join(f"{k} 0 0\n" for k in range(5))
        + "kids 0\n"
    )
    mesh = parse_ac3d(_world(text))
    assert mesh.faces.tolist() == [[0, 1, 2], [0, 2, 3], [0, 3, 4]]
    assert _area(mesh) == pytest.approx(2.5 * np.sin(2 * np.pi / 5), rel=1e-5)


def test_loc_and_rot_compose_down_the_hierarchy() -> None:
    # the parent turns +x into +y (v @ R) and moves by (10, 0, 0); the child moves by (0, 0, 5)
    child = _quad(extra="loc 0 0 5\n")
    parent = "OBJECT group\nrot 0 1 0  -1 0 0  0 0 1\nloc 10 0 0\nkids 1\n" + child
    mesh = parse_ac3d(_world(parent))
    # child vertex (1, 0, 0) -> (1, 0, 5) -> rotated (0, 1, 5) -> moved (10, 1, 5)
    assert mesh.vertices[1] == pytest.approx([10, 1, 5])
    assert mesh.vertices[3] == pytest.approx([9, 0, 5])  # (0, 1, 0) -> (-1, 0, 5) + 10


def test_siblings_do_not_inherit_each_others_transforms() -> None:
    mesh = parse_ac3d(_world(_quad(extra="loc 5 0 0\n"), _quad()))
    assert mesh.vertices[:4, 0].min() == 5 and mesh.vertices[4:, 0].min() == 0
    assert len(mesh.faces) == 4 and mesh.faces.max() == 7


def test_line_surfaces_are_skipped_and_counted() -> None:
    lines = (
        "OBJECT poly\nnumvert 3\n0 0 0\n1 0 0\n0 1 0\nnumsurf 3\n"
        "SURF 0x21\nmat 0\nrefs 3\n0 0 0\n1 0 0\n2 0 0\n"  # closed line (flags above bit 4 too)
        "SURF 0x02\nmat 0\nrefs 2\n0 0 0\n1 0 0\n"  # line
        "SURF 0x30\nmat 0\nrefs 3\n0 0 0\n1 0 0\n2 0 0\n"  # polygon, shaded and two-sided
        "kids 0\n"
    )
    mesh = parse_ac3d(_world(lines))
    assert mesh.faces.tolist() == [[0, 1, 2]]
    assert mesh.skipped == {"closed_line": 1, "line": 1}


def test_torcs_acc_normals_multitexture_and_strips() -> None:
    # .acc: six numbers a vertex (position, normal), four texture lines, refs with four
    # uv pairs, and SURF type 4, a triangle strip with a repeated (joining) vertex
    acc = (
        'OBJECT poly\nname "BODY"\ntexture "car.rgb" base\ntexture "car.rgb" tiled\n'
        'texture "car.rgb" skids\ntexture "car.rgb" shad\nnumvert 4\n'
        "0 0 0 0 1 0\n1 0 0 0 1 0\n0 0 1 0 1 0\n1 0 1 0 1 0\nnumsurf 1\nSURF 0x14\nmat 0\n"
        "refs 5\n"
        + "".join(f"{k} 0.1 0.2 0.3 0.4 0.5 0.6 0.7 0.8\n" for k in (0, 1, 2, 3, 3))
        + "kids 0\n"
    )
    mesh = parse_ac3d(_world(acc))
    assert sorted(map(sorted, mesh.faces.tolist())) == [[0, 1, 2], [1, 2, 3]]
    assert _area(mesh) == pytest.approx(1.0)


def test_blank_and_comment_lines_and_data_blocks_are_stepped_over() -> None:
    text = _quad(extra="data 11\nhello\nworld\n# a comment\n").replace("refs 4\n", "refs 4\n\n")
    mesh = parse_ac3d(_world(text))
    assert len(mesh.faces) == 2


def test_a_parent_declaring_more_kids_than_the_file_has_keeps_what_is_there() -> None:
    mesh = parse_ac3d(_world(_quad(), kids=3))
    assert len(mesh.faces) == 2 and mesh.skipped["missing_kids"] == 2


def test_a_truncated_file_names_the_file_and_line(tmp_path: Path) -> None:
    data = _world(_quad())
    cut = data[: data.index(b"refs 4") + 14]  # inside the references
    path = tmp_path / "cut.ac"
    path.write_bytes(cut)
    with pytest.raises(DataError, match=r"cut\.ac: line \d+: refs 4 declares more than"):
        read_ac3d(path)
    path.write_bytes(data[: data.index(b"numsurf")])
    with pytest.raises(DataError, match=r"cut\.ac: truncated file"):
        read_ac3d(path)


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ("numvert 4", "numvert 400", r"line 7: numvert 400 declares more than the 13 lines left"),
        ("numsurf 1", "numsurf 9", r"line 12: numsurf 9 declares more than"),
        ("refs 4", "refs 3", r"line 19: '3 0 1' is no statement \(more vertices or references"),
        ("numvert 4", "numvert 3", r"line 11: '0 1 0' is no statement"),
        ("3 0 1\n", "7 0 1\n", r"line 19: reference to vertex 7, but the object has 4 vertices"),
        ("numvert 4", "numvert -1", r"line 7: numvert -1 is negative"),
        ("1 0 0\n1 1 0", "1 0 0\n1 one 0", r"line 10: a vertex line needs 3 numbers"),
        ("kids 0", "kids lots", r"line 20: kids is not a count: 'lots'"),
    ],
)
def test_a_count_or_value_that_lies_is_refused_with_its_line(
    old: str, new: str, message: str
) -> None:
    text = _world(_quad()).decode().replace(old, new, 1)
    with pytest.raises(DataError, match=rf"forged\.ac: {message}"):
        parse_ac3d(text.encode(), "forged.ac")


def test_not_ac3d_and_too_deep_are_refused() -> None:
    with pytest.raises(DataError, match="not an AC3D file"):
        parse_ac3d(b"ply\n", "x.ac")
    with pytest.raises(DataError, match="no OBJECT"):
        parse_ac3d(HEADER.encode(), "x.ac")
    nested = "".join("OBJECT group\nkids 1\n" for _ in range(70)) + _quad()
    with pytest.raises(DataError, match="nest more than 64 deep"):
        parse_ac3d(_world(nested), "x.ac")


def test_light_objects_and_empty_groups_add_no_geometry() -> None:
    light = "OBJECT light\nloc 0 5 0\nkids 0\n"
    mesh = parse_ac3d(_world(light, "OBJECT group\nkids 0\n", _quad()))
    assert len(mesh.vertices) == 4 and mesh.objects == 4
