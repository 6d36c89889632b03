"""Forged ONNX models are refused before ONNX Runtime runs them (issue 36, class 6)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from pfnet.errors import DataError
from pfnet.inference.onnx_graph import check_graph

onnx = pytest.importorskip("onnx")  # to forge the files; the check itself needs no onnx
from onnx import TensorProto, helper  # noqa: E402

SHIPPED = Path(__file__).parents[1] / "python/pfnet/weights/sh3d-small.onnx"


def _model(nodes, initializers=(), path: Path | None = None) -> Path:
    """A file with a pfnet export's metadata and signature around ``nodes``."""
    graph = helper.make_graph(
        nodes,
        "forged",
        [helper.make_tensor_value_info("partial", TensorProto.FLOAT, ["batch", "points", 3])],
        [helper.make_tensor_value_info("detail", TensorProto.FLOAT, ["batch", 512, 3])],
        initializer=list(initializers),
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 20)])
    meta = {"format": "pfnet-onnx", "version": "1", "n_points": "2048", "n_missing": "512"}
    meta["config"] = "{}"
    helper.set_model_props(model, meta)
    onnx.save(model, path)
    return path


def _loop(tmp_path: Path) -> Path:
    body = helper.make_graph(
        [helper.make_node("Identity", ["cond"], ["cond_out"])],
        "body",
        [
            helper.make_tensor_value_info("i", TensorProto.INT64, []),
            helper.make_tensor_value_info("cond", TensorProto.BOOL, []),
        ],
        [helper.make_tensor_value_info("cond_out", TensorProto.BOOL, [])],
    )
    trips = helper.make_tensor("trips", TensorProto.INT64, [], [2**62])
    keep = helper.make_tensor("keep", TensorProto.BOOL, [], [True])
    nodes = [
        helper.make_node("Loop", ["trips", "keep"], [], body=body),
        helper.make_node("Identity", ["partial"], ["detail"]),
    ]
    return _model(nodes, [trips, keep], tmp_path / "loop.onnx")


def test_the_exports_pass(tmp_path):
    check_graph(SHIPPED)


def test_a_loop_is_refused(tmp_path):
    with pytest.raises(DataError, match=r"loop\.onnx uses the operator 'Loop', which no pfnet"):
        check_graph(_loop(tmp_path))


def test_constant_of_shape_is_refused(tmp_path):
    shape = helper.make_tensor("shape", TensorProto.INT64, [1], [400_000_000])
    nodes = [
        helper.make_node("ConstantOfShape", ["shape"], ["big"]),
        helper.make_node("Identity", ["partial"], ["detail"]),
    ]
    with pytest.raises(DataError, match=r"operator 'ConstantOfShape'"):
        check_graph(_model(nodes, [shape], tmp_path / "c.onnx"))


@pytest.mark.parametrize("split", [False, True])
def test_an_allowed_operator_with_a_huge_constant_shape_is_refused(tmp_path, split):
    if split:  # two harmless constants joined into one shape
        parts = [helper.make_tensor(f"s{i}", TensorProto.INT64, [1], [40_000]) for i in (0, 1)]
        nodes = [helper.make_node("Concat", ["s0", "s1"], ["shape"], axis=0)]
    else:
        parts = [helper.make_tensor("shape", TensorProto.INT64, [2], [40_000, 40_000])]
        nodes = []
    nodes += [
        helper.make_node("Expand", ["partial", "shape"], ["big"]),
        helper.make_node("Identity", ["partial"], ["detail"]),
    ]
    with pytest.raises(DataError, match=r"would, as a shape, make 1,600,000,000 elements"):
        check_graph(_model(nodes, parts, tmp_path / "e.onnx"))


def test_another_domain_and_local_functions_are_refused(tmp_path):
    nodes = [helper.make_node("Relu", ["partial"], ["detail"], domain="com.example")]
    with pytest.raises(DataError, match=r"operator 'com.example.Relu'"):
        check_graph(_model(nodes, path=tmp_path / "d.onnx"))


def test_not_a_protobuf_is_one_line(tmp_path):
    path = tmp_path / "junk.onnx"
    path.write_bytes(b"\xff" * 64)
    with pytest.raises(DataError, match=r"junk\.onnx cannot be read"):
        check_graph(path)


def test_complete_with_a_forged_loop_model_is_refused_not_hung(tmp_path):
    pytest.importorskip("onnxruntime")
    (tmp_path / "scan.xyz").write_text("0 0 0\n1 0 0\n0 1 0\n0 0 1\n")
    model = _loop(tmp_path)
    done = subprocess.run(
        [sys.executable, "-m", "pfnet.cli", "complete", "scan.xyz", "--checkpoint", str(model)]
        + ["--out", "out"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 1
    assert "uses the operator 'Loop'" in done.stderr
    assert "Traceback" not in done.stderr
