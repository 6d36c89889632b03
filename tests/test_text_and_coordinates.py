"""Real-world text clouds and coordinates (issue 36, class 5)."""

from __future__ import annotations

import numpy as np
import pytest

from pfnet.errors import DataError
from pfnet.io.clouds import read_point_cloud
from pfnet.io.formats.meshes import check_mesh_file


def _read(tmp_path, text: str, name: str = "c.xyz", **kwargs) -> np.ndarray:
    path = tmp_path / name
    path.write_text(text)
    return read_point_cloud(path, **kwargs)


def test_decimal_commas_are_read_as_decimals(tmp_path):
    points = _read(tmp_path, "10,1257 19,7358 31,9213\n-1,5\t2,25\t3,0\n")
    np.testing.assert_allclose(points, [[10.1257, 19.7358, 31.9213], [-1.5, 2.25, 3.0]], rtol=1e-6)
    semicolons = _read(tmp_path, "x;y;z\n1,5;2,5;3,5;7\n", name="s.txt")
    np.testing.assert_allclose(semicolons, [[1.5, 2.5, 3.5]])


@pytest.mark.parametrize("text", ["1,2,3\n4,5,6\n", "1, 2, 3\n4, 5, 6\n", "1 2 3\n4 5 6\n"])
def test_comma_separated_values_are_still_columns(tmp_path, text):
    np.testing.assert_array_equal(_read(tmp_path, text), [[1, 2, 3], [4, 5, 6]])


def test_a_decimal_comma_file_with_a_stray_line_names_it(tmp_path):
    with pytest.raises(DataError, match=r"line 2 has 1 column\(s\)"):
        _read(tmp_path, "1,5 2,5 3,5\n1,2,3\n")


def test_a_header_orders_the_columns(tmp_path):
    points = _read(tmp_path, "z,y,x\n3,2,1\n6,5,4\n")
    np.testing.assert_array_equal(points, [[1, 2, 3], [4, 5, 6]])
    with_attributes = _read(tmp_path, "id X Y Z intensity\n9 1 2 3 0.5\n", name="a.txt")
    np.testing.assert_array_equal(with_attributes, [[1, 2, 3]])
    np.testing.assert_array_equal(_read(tmp_path, "a b c\n1 2 3\n", name="b.txt"), [[1, 2, 3]])
    with pytest.raises(DataError, match=r"line 1 names the columns .* but no z"):
        _read(tmp_path, "x y w\n1 2 3\n", name="d.txt")


def test_a_leica_count_then_names(tmp_path):
    np.testing.assert_array_equal(_read(tmp_path, "1\nz y x\n3 2 1\n", name="l.pts"), [[1, 2, 3]])


def test_an_obj_whose_vertex_lines_mix_widths_is_refused_naming_the_line(tmp_path):
    path = tmp_path / "m.obj"
    path.write_text("v 0 0 0\nv 1 0 0 0.5 0.5 0.5\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(DataError, match=r"m\.obj: line 2 is a vertex of 6 values, line 1 one of 3"):
        check_mesh_file(path)
    path.write_text("v 0 0 0 1 0 0\nv 1 0 0 0 1 0  # red, green\nvn 0 0 1\nf 1 2 1\n")
    check_mesh_file(path)  # one width (colours on every line) is fine


UTM = np.array([[512345.0, 5412345.0, 100.0], [512349.0, 5412345.3, 101.5]], dtype=np.float64)


def test_text_and_float64_keep_their_digits_when_asked(tmp_path):
    np.savetxt(tmp_path / "utm.xyz", UTM, fmt="%.3f")
    np.save(tmp_path / "utm.npy", UTM)
    for name in ("utm.xyz", "utm.npy"):
        kept = read_point_cloud(tmp_path / name, keep_float64=True)
        assert kept.dtype == np.float64
        np.testing.assert_array_equal(kept, UTM)
        assert read_point_cloud(tmp_path / name).dtype == np.float32  # the default


def test_points_that_float32_makes_one_are_said_to_be_so(tmp_path):
    far = np.array([[1e9, 0, 0], [1e9 + 1, 0, 0], [1e9 + 2, 0, 0]], dtype=np.float64)
    np.save(tmp_path / "far.npy", far)
    with pytest.raises(DataError, match=r"span 2 but lie 1e\+09 from the origin.*float32"):
        read_point_cloud(tmp_path / "far.npy")
    assert len(np.unique(read_point_cloud(tmp_path / "far.npy", keep_float64=True), axis=0)) == 3
    np.save(tmp_path / "same.npy", np.ones((3, 3)))
    assert read_point_cloud(tmp_path / "same.npy").shape == (3, 3)  # truly one point: read
