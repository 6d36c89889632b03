"""The tenth hostile audit's protocol findings: a benchmark protocol run on a data set it does
not define (a ShapeNet-55 number from 512-point clouds), a NaN ``--missing-ratio``, PyTorch's
``weights_only=False`` advice relayed for an unreadable checkpoint, a manifest larger than its
own reader accepts, and ``predict --out`` writing into a data set or another run's folder."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from pfnet.checkpoint import read_checkpoint  # noqa: E402
from pfnet.cli import main  # noqa: E402
from pfnet.errors import DataError  # noqa: E402


class Foreign:
    """A class a weights-only load refuses to unpickle."""


def test_unreadable_checkpoint_never_relays_weights_only_advice(tmp_path, capsys):
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"garbage\n")
    foreign = tmp_path / "foreign.pt"
    torch.save({"x": Foreign()}, foreign)
    for path in (junk, foreign):
        with pytest.raises(DataError, match="cannot be read: not a pfnet checkpoint") as err:
            read_checkpoint(path)
        assert "weights_only" not in str(err.value)
        assert "never unpickles code" in str(err.value)
    onnx = tmp_path / "m.onnx"
    onnx.write_bytes(b"\x08\x07garbage")
    with pytest.raises(DataError, match=r"m\.onnx cannot be read: it is an ONNX model"):
        read_checkpoint(onnx)
    out = tmp_path / "o"
    args = ["predict", "--checkpoint", str(junk), "--data", str(tmp_path), "--out", str(out)]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "weights_only" not in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("ratio", ["nan", "inf", "0", "1", "0.3"])
def test_evaluate_shapenet55_refuses_a_ratio_it_does_not_define(tmp_path, ratio, capsys):
    pred = tmp_path / "pred"
    pred.mkdir()
    args = ["evaluate", str(pred), "--data", str(tmp_path), "--protocol", "shapenet55"]
    assert main([*args, "--missing-ratio", ratio]) == 1
    err = capsys.readouterr().err
    if ratio == "0.3":
        assert "--missing-ratio of the shapenet55 protocol is one of 0.25, 0.5, 0.75" in err
    else:
        assert f"--missing-ratio must be in (0, 1), got {float(ratio)}" in err
