"""The eighth hostile audit's model-side findings: forged ONNX graphs (a declared or actual
output that is not ``(batch, M, 3)`` finite points, a run that fails), weights that overflow
in the forward pass, and data sets whose clouds are not the model's size. Each ends in one
line naming the model (or the data set) and the problem, and nothing is written."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from forge import onnx_model, resized_dataset

from pfnet.cli import main
from pfnet.io.clouds import write_ply


@pytest.fixture
def checkpoint(tmp_path: Path) -> Path:
    """A tiny untrained PF-Net for 512-point clouds (it takes 384, predicts 128)."""
    pytest.importorskip("torch")
    from pfnet.inference.checkpoint import save_checkpoint
    from pfnet.models import build_model
    from pfnet.training.config import preset_config

    config = preset_config("small").replace(n_points=512, width=0.125)
    path = tmp_path / "m.pt"
    save_checkpoint(path, {"config": config.to_dict(), "model": build_model(config).state_dict()})
    return path


@pytest.fixture
def scan(tmp_path: Path) -> Path:
    path = tmp_path / "scan.ply"
    write_ply(path, np.random.default_rng(0).normal(size=(300, 3)).astype(np.float32))
    return path


def _one_line_error(capsys, *names: str) -> str:
    err = capsys.readouterr().err
    # complete's note on the model's frame may come first; the error is one line
    err = "".join(line for line in err.splitlines(True) if not line.startswith("note: "))
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    for name in names:
        assert name in err, err
    return err


def _forged_graphs(folder: Path) -> dict[str, tuple[Path, str]]:
    """Forged models and the message each gets: the first ones declare an output pfnet
    refuses on loading, the others declare the right one and misbehave when run."""
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    from onnx import TensorProto, helper, numpy_helper

    def const(name: str, values, dtype=np.int64):
        return numpy_helper.from_array(np.array(values, dtype), name)

    def filled(value: float, shape_input: str = "s", dtype=TensorProto.FLOAT):
        # Expand of a constant: ConstantOfShape is refused before the signature is read
        # (pfnet.inference.onnx_graph: no pfnet export uses it)
        tensor = helper.make_tensor("v", dtype, [1], [value])
        return [
            helper.make_node("Constant", [], ["value"], value=tensor),
            helper.make_node("Expand", ["value", shape_input], ["detail"]),
        ]

    shape = helper.make_node("Shape", ["partial"], ["s"])
    first_128 = helper.make_node("Slice", ["partial", "start", "end", "axis"], ["head"])
    head = (const("start", [0]), const("end", [128]), const("axis", [1]))
    scaled = [first_128, helper.make_node("Mul", ["head", "k"], ["detail"])]
    return {  # name: (file, message)
        "many.onnx": (  # 3,000,000 points at 1e30 were once written with exit code 0
            onnx_model(
                folder / "many.onnx",
                filled(1e30),
                detail_shape=[1, 3_000_000, 3],
                initializers=(const("s", [1, 3_000_000, 3]),),
            ),
            "detail is declared tensor(float) [1, 3000000, 3], but pfnet expects "
            "tensor(float) (batch, 128, 3)",
        ),
        "f64.onnx": (
            onnx_model(
                folder / "f64.onnx",
                filled(0.5, dtype=TensorProto.DOUBLE),
                detail_type=TensorProto.DOUBLE,
                initializers=(const("s", [1, 128, 3]),),
            ),
            "detail is declared tensor(double)",
        ),
        "rank1.onnx": (
            onnx_model(
                folder / "rank1.onnx",
                filled(0.5),
                detail_shape=[3],
                initializers=(const("s", [3]),),
            ),
            "detail is declared tensor(float) [3]",
        ),
        "echo.onnx": (  # declared (batch, 128, 3), gives (batch, 384, 3)
            onnx_model(folder / "echo.onnx", [shape, *filled(0.5)]),
            "predicted float32 (1, 384, 3), not float (1, 128, 3)",
        ),
        "alloc.onnx": (  # asks ONNX Runtime for 10^16 bytes when run
            onnx_model(
                folder / "alloc.onnx",
                [shape, helper.make_node("Mul", ["s", "k"], ["big"]), *filled(0.5, "big")],
                initializers=(const("k", [2**30, 2**10, 1]),),
            ),
            "the constant 'k' [1073741824, 1024, 1] would, as a shape, make",  # refused first
        ),
        "alloc-run.onnx": (  # a factor the graph check lets by: ORT fails to run it
            onnx_model(
                folder / "alloc-run.onnx",
                [shape, helper.make_node("Mul", ["s", "k"], ["big"]), *filled(0.5, "big")],
                initializers=(const("k", [2**14, 2**14, 1]),),
            ),
            "failed to run: ",
        ),
        "nan.onnx": (
            onnx_model(
                folder / "nan.onnx",
                scaled,
                initializers=(*head, const("k", [np.nan], np.float32)),
            ),
            "predicted NaN or infinite coordinates",
        ),
        "far.onnx": (
            onnx_model(
                folder / "far.onnx", scaled, initializers=(*head, const("k", [1e30], np.float32))
            ),
            "predicted a coordinate of",
        ),
    }


def test_forged_onnx_models_are_refused_in_one_line(tmp_path: Path, scan: Path, capsys) -> None:
    for name, (model, message) in _forged_graphs(tmp_path).items():
        out = tmp_path / f"out-{name}"
        assert main(["complete", str(scan), "--checkpoint", str(model), "--out", str(out)]) == 1
        _one_line_error(capsys, name, message)
        assert not out.exists(), name  # nothing written, not even an empty folder


def test_predict_refuses_an_onnx_output_that_ignores_the_batch(
    tmp_path: Path, tiny_dataset: Path, capsys
) -> None:
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    from onnx import helper, numpy_helper

    def const(name: str, values):
        return numpy_helper.from_array(np.array(values, np.int64), name)

    model = onnx_model(  # detail = partial[:1, :128]: declared (batch, 128, 3), one cloud
        tmp_path / "one.onnx",
        [
            helper.make_node("Slice", ["partial", "zero", "one", "zero"], ["first"]),
            helper.make_node("Slice", ["first", "zero", "m", "one"], ["detail"]),
        ],
        initializers=(const("zero", [0]), const("one", [1]), const("m", [128])),
    )
    out = tmp_path / "pred"
    args = ["predict", "--checkpoint", str(model), "--data", str(tiny_dataset), "--out", str(out)]
    assert main([*args, "--batch-size", "4"]) == 1
    _one_line_error(capsys, "one.onnx", "predicted float32 (1, 128, 3), not float (4, 128, 3)")
    assert not out.exists()


def test_weights_that_overflow_are_refused_before_writing(
    tmp_path: Path, tiny_dataset: Path, checkpoint: Path, scan: Path, capsys
) -> None:
    import torch

    state = torch.load(checkpoint, weights_only=True)
    for value in state["model"].values():
        if value.is_floating_point():
            value.mul_(1e30)  # finite weights whose products overflow float32
    big = tmp_path / "big.pt"
    torch.save(state, big)
    pred, out = tmp_path / "pred", tmp_path / "out"
    args = ["predict", "--checkpoint", str(big), "--data", str(tiny_dataset), "--out", str(pred)]
    assert main([*args, "--device", "cpu"]) == 1
    _one_line_error(capsys, "big.pt", "predicted NaN or infinite coordinates")
    assert not pred.exists()  # no NaN predictions for evaluate to trip over
    args = ["complete", str(scan), "--checkpoint", str(big), "--out", str(out)]
    assert main([*args, "--device", "cpu"]) == 1
    err = _one_line_error(capsys, "big.pt", "predicted NaN or infinite coordinates")
    assert "write_ply" not in err  # the model is blamed, not the writer
    assert not out.exists()


@pytest.mark.parametrize("n_points", [3, 6, 600])
def test_predict_refuses_clouds_of_another_size_than_the_models(
    tmp_path: Path, tiny_dataset: Path, checkpoint: Path, n_points: int, capsys
) -> None:
    data = resized_dataset(tmp_path / "data", tiny_dataset, n_points)
    out = tmp_path / "pred"
    args = ["predict", "--checkpoint", str(checkpoint), "--data", str(data), "--out", str(out)]
    assert main([*args, "--device", "cpu"]) == 1
    _one_line_error(capsys, f"has clouds of {n_points} points", "m.pt", "clouds of 512")
    assert not out.exists()


def test_predict_refuses_a_ratio_that_leaves_the_encoder_too_few_points(
    tmp_path: Path, tiny_dataset: Path, checkpoint: Path, capsys
) -> None:
    out = tmp_path / "pred"
    args = ["predict", "--checkpoint", str(checkpoint), "--data", str(tiny_dataset)]
    assert main([*args, "--out", str(out), "--missing-ratio", "0.995", "--device", "cpu"]) == 1
    _one_line_error(capsys, "removes 509 points", "4 must remain")
    assert not out.exists()
