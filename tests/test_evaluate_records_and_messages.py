"""evaluate against its folder's record, two files for one sample, and messages (issue 36,
class 7)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from pfnet.cli import _one_line, main
from pfnet.errors import DataError
from pfnet.evaluation.scoring import find_prediction_files
from pfnet.io.clouds import save_npy, write_ply


def test_two_files_for_one_sample_are_refused_naming_both(tmp_path):
    (tmp_path / "chair").mkdir()
    save_npy(tmp_path / "chair" / "x.npy", np.zeros((4, 3)))
    write_ply(tmp_path / "chair" / "x.ply", np.ones((4, 3)))
    save_npy(tmp_path / "chair" / "y.npy", np.zeros((4, 3)))
    with pytest.raises(DataError, match=r"chair/x\.npy and .*chair/x\.ply are two predictions"):
        find_prediction_files(tmp_path)


def test_pred_is_complete_against_a_missing_region_record_is_refused(tmp_path, capsys):
    pytest.importorskip("torch")
    from pfnet.data import prepare_dataset

    data, pred = tmp_path / "data", tmp_path / "pred"
    prepare_dataset(None, data, format="procedural", points=2048, seed=0, count=3,
                    categories=["chair", "table"], workers=1, progress=False)  # fmt: skip
    assert main(["predict", "--data", str(data), "--out", str(pred), "--device", "cpu"]) == 0
    capsys.readouterr()
    argv = ["evaluate", str(pred), "--data", str(data), "--region", "whole"]
    assert main([*argv, "--pred-is-complete"]) == 1
    err = capsys.readouterr().err
    assert f"{pred / 'predictions.json'} records the pfnet protocol" in err
    assert "drop --pred-is-complete" in err
    assert main([*argv, "--pred-is-complete", "--ignore-recorded-protocol"]) == 0


def test_an_oserror_with_a_message_only_keeps_it():
    err = OSError("disk full while writing the array")
    err.filename = "out/x.npy"  # as atomic_path names the output
    assert str(err) == "[Errno None] None: 'out/x.npy'"  # what was printed
    assert _one_line(err) == "disk full while writing the array: out/x.npy"
    assert _one_line(OSError(28, "No space left on device", "a.npy")) == (
        "No space left on device: a.npy"
    )


def test_a_full_disk_in_prepare_names_the_data_set_not_its_temporary_folder(
    tiny_dataset, tmp_path, monkeypatch
):
    from pfnet.data import format as data_format
    from pfnet.data import load_split

    splits = {s: load_split(tiny_dataset, s) for s in ("train", "val", "test")}

    def full(path, arrays):
        raise OSError(28, "No space left on device", str(path))

    monkeypatch.setattr(data_format, "write_npz", full)
    with pytest.raises(OSError) as caught:
        data_format.write_dataset(tmp_path / "data", splits, {})
    assert caught.value.filename == str(tmp_path / "data")
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_a_pickled_pt_is_one_line_without_a_torch_warning(tmp_path, capsys):
    pytest.importorskip("torch")
    import pickle

    class Evil:
        def __reduce__(self):
            return (print, ("unpickled",))

    path = tmp_path / "evil.pt"
    path.write_bytes(pickle.dumps({"config": {}, "model": Evil()}, protocol=4))
    (tmp_path / "scan.xyz").write_text("0 0 0\n1 0 0\n0 1 0\n")
    argv = ["complete", str(tmp_path / "scan.xyz"), "--checkpoint", str(path)]
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")  # as a terminal shows them, not pytest's "error"
        assert main([*argv, "--out", str(tmp_path / "out")]) == 1
    assert [str(w.message) for w in shown] == []
    captured = capsys.readouterr()
    assert "unpickled" not in captured.out
    assert captured.err.strip().splitlines() == [captured.err.strip()]
    assert "cannot be read" in captured.err and "Warning" not in captured.err


def test_a_file_named_like_a_shipped_model_does_not_replace_it(tmp_path, monkeypatch):
    from pfnet.errors import ConfigError
    from pfnet.inference.shipped import DEFAULT_MODEL, WEIGHTS_DIR, resolve_checkpoint

    monkeypatch.chdir(tmp_path)
    shipped = WEIGHTS_DIR / f"{DEFAULT_MODEL}.safetensors"
    assert resolve_checkpoint(DEFAULT_MODEL) == shipped
    (tmp_path / DEFAULT_MODEL).write_bytes(b"someone else's")
    with pytest.raises(ConfigError, match=r"both a file in this folder and a shipped model"):
        resolve_checkpoint(DEFAULT_MODEL)
    assert resolve_checkpoint(f"./{DEFAULT_MODEL}") == Path(DEFAULT_MODEL)
    assert resolve_checkpoint(f"shipped:{DEFAULT_MODEL}") == shipped
    with pytest.raises(ConfigError, match=r"no shipped model 'nope'"):
        resolve_checkpoint("shipped:nope")


@pytest.mark.parametrize(
    ("source", "name", "said"),
    [
        ("sh3d-small.onnx", "m.pt", "m.pt is an ONNX model, not a PyTorch checkpoint"),
        ("sh3d-small.safetensors", "m.pt", "is a safetensors model file, not a PyTorch"),
        ("zip", "m.safetensors", "is a PyTorch checkpoint, not a safetensors model file"),
        ("zip", "m.onnx", "m.onnx is a PyTorch checkpoint, not an ONNX model"),
    ],
)
def test_a_model_file_with_the_wrong_suffix_is_named_as_what_it_is(tmp_path, source, name, said):
    from pfnet.errors import ConfigError
    from pfnet.inference.shipped import WEIGHTS_DIR, resolve_checkpoint

    path = tmp_path / name
    if source == "zip":  # what torch.save writes starts as a zip archive
        path.write_bytes(b"PK\x03\x04" + bytes(60))
    else:
        path.write_bytes((WEIGHTS_DIR / source).read_bytes())
    with pytest.raises(ConfigError, match=rf"{said}.*; rename it to m\."):
        resolve_checkpoint(path)
