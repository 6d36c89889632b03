"""Hostile files: readers check the sizes a file declares against the bytes it has before they
allocate or loop, and every command turns a bad file into one line naming it."""

from __future__ import annotations

import contextlib
import errno
import io
import signal
import struct
import zipfile
from pathlib import Path

import numpy as np
import pytest
from forge import write_predictions

from pfnet.cli import main
from pfnet.data import load_split
from pfnet.errors import DataError
from pfnet.io import read_point_cloud, write_ply


@contextlib.contextmanager
def _deadline(seconds: int):
    """Fail instead of hanging: a regression here used to loop forever."""

    def expire(*_):
        raise AssertionError(f"still running after {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def _ply_with_forged_faces(path: Path, faces: int, list_length: int) -> Path:
    header = (
        f"ply\nformat binary_little_endian 1.0\nelement face {faces}\n"
        "property list char int vertex_indices\nelement vertex 2\n"
        "property float x\nproperty float y\nproperty float z\nend_header\n"
    )
    body = struct.pack("<b", list_length) + struct.pack("<3i", 0, 1, 0) * 4
    path.write_bytes(header.encode() + body + np.zeros(6, "<f4").tobytes())
    return path


@pytest.mark.parametrize(("faces", "length"), [(10**12, 3), (3, -1), (2**40, -128)])
def test_forged_ply_counts_are_refused_at_once(tmp_path: Path, faces: int, length: int) -> None:
    path = _ply_with_forged_faces(tmp_path / "forged.ply", faces, length)
    with _deadline(30), pytest.raises(DataError, match="forged.ply: (truncated|negative)"):
        read_point_cloud(path)


def _pcd_compressed(path: Path, points: int, raw: int, payload: bytes) -> Path:
    header = (
        "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {points}\nHEIGHT 1\nPOINTS {points}\nDATA binary_compressed\n"
    )
    path.write_bytes(header.encode() + struct.pack("<II", len(payload), raw) + payload)
    return path


def test_compressed_pcd_sizes_are_checked_before_and_while_expanding(tmp_path: Path) -> None:
    # 1 literal byte, then back references of 264 bytes each: ~88x expansion per 3 bytes
    bomb = b"\x00\x00" + b"\xe0\xff\x00" * 20_000
    lie = _pcd_compressed(tmp_path / "lie.pcd", 1000, 5_000_000, bomb)
    with _deadline(30), pytest.raises(DataError, match="declares 5000000 bytes, the header's"):
        read_point_cloud(lie)
    consistent = _pcd_compressed(tmp_path / "bomb.pcd", 1000, 12_000, bomb)
    with _deadline(30), pytest.raises(DataError, match="expands beyond the declared 12000"):
        read_point_cloud(consistent)


def _npy_claiming(shape: tuple[int, ...]) -> bytes:
    stream = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        stream, {"descr": "<f4", "fortran_order": False, "shape": shape}
    )
    return stream.getvalue() + np.zeros(30, "<f4").tobytes()


def test_npy_headers_claiming_huge_shapes_are_refused(tmp_path: Path) -> None:
    path = tmp_path / "huge.npy"
    path.write_bytes(_npy_claiming((10**12, 3)))
    with pytest.raises(
        DataError, match=r"huge.npy: the .npy header declares shape \(1000000000000, 3\)"
    ):
        read_point_cloud(path)


def test_npz_members_claiming_huge_shapes_are_refused(tmp_path: Path, tiny_dataset: Path) -> None:
    import shutil

    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    with zipfile.ZipFile(data / "test.npz", "w") as archive:
        archive.writestr("points.npy", _npy_claiming((10**12, 512, 3)))
        archive.writestr("category.npy", _npy_claiming((1,)))
        archive.writestr("name.npy", _npy_claiming((1,)))
    with pytest.raises(DataError, match="member points.npy: the .npy header declares"):
        load_split(data, "test")


def test_one_bad_file_does_not_stop_a_complete_batch(tmp_path: Path, capsys) -> None:
    torch = pytest.importorskip("torch")
    from pfnet.checkpoint import save_checkpoint
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
    (tmp_path / "huge.npy").write_bytes(_npy_claiming((10**12, 3)))
    forged = _ply_with_forged_faces(tmp_path / "forged.ply", 10**12, 3)
    out = tmp_path / "out"
    args = ["complete", str(good), str(tmp_path / "huge.npy"), str(forged), "--out", str(out)]
    with _deadline(60):
        assert main([*args, "--checkpoint", str(checkpoint), "--device", "cpu"]) == 2
    captured = capsys.readouterr()
    assert "completed 1 of 3" in captured.out
    assert "huge.npy" in captured.err and "forged.ply" in captured.err
    assert "Traceback" not in captured.err
    assert sorted(p.name for p in out.iterdir()) == ["good_completed.ply", "good_missing.ply"]


def test_damaged_checkpoints_are_one_line_errors(tmp_path: Path, capsys) -> None:
    torch = pytest.importorskip("torch")
    from pfnet.checkpoint import FORMAT, VERSION, save_checkpoint
    from pfnet.models import build_model
    from pfnet.training.config import preset_config

    config = preset_config("small").replace(n_points=512, width=0.125)
    model = build_model(config)
    scan = tmp_path / "scan.ply"
    write_ply(scan, np.random.default_rng(0).normal(size=(400, 3)).astype(np.float32))
    cases = {
        "no-model.pt": ({"config": config.to_dict()}, "has no 'model' table"),
        "no-config.pt": ({"model": model.state_dict()}, "has no 'config' table"),
        "huge.pt": (
            {"config": {**config.to_dict(), "n_points": 10**12}, "model": model.state_dict()},
            "n_points",
        ),
    }
    weights = model.state_dict()
    weights[next(k for k in weights if k.endswith("weight"))].fill_(float("nan"))
    cases["nan.pt"] = ({"config": config.to_dict(), "model": weights}, "NaN or infinite weights")
    for name, (state, message) in cases.items():
        path = tmp_path / name
        if name == "no-config.pt":  # save_checkpoint adds the format keys; forge it by hand
            torch.save({"format": FORMAT, "version": VERSION, **state}, path)
        else:
            save_checkpoint(path, state)
        out = tmp_path / f"out-{name}"
        assert main(["complete", str(scan), "--checkpoint", str(path), "--out", str(out)]) == 1
        err = capsys.readouterr().err
        assert message in err and name in err and "Traceback" not in err, err
        assert not out.exists() or not any(out.iterdir())


def test_io_failures_are_one_line_errors(
    tmp_path: Path, tiny_dataset: Path, capsys, monkeypatch
) -> None:
    import pfnet.evaluate

    pred = write_predictions(tmp_path / "pred", tiny_dataset)

    def full_disk(*_args, **_kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "m.json"))

    monkeypatch.setattr(pfnet.evaluate, "write_json", full_disk)
    args = ["evaluate", str(pred), "--data", str(tiny_dataset), "--json", str(tmp_path / "m.json")]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert err.strip().endswith("No space left on device: " + str(tmp_path / "m.json")), err


def test_a_symlink_loop_among_prediction_folders_is_named_and_skipped(
    tmp_path: Path, tiny_dataset: Path, capsys
) -> None:
    pred = write_predictions(tmp_path / "pred", tiny_dataset, skip=("chair",))
    split = load_split(tiny_dataset, "test")
    (pred / "chair").symlink_to(pred / "chair")  # the chair folder is a loop
    with _deadline(30):
        code = main(["evaluate", str(pred), "--data", str(tiny_dataset), "--missing-ratio", "0.25"])
    assert code == 2  # the chairs are missing; the rest is scored
    captured = capsys.readouterr()
    assert captured.err.count(f"skipped {pred / 'chair'}") == 1
    assert "Too many levels of symbolic links" in captured.err
    n_chairs = int((split.category == "chair").sum())
    assert f"{len(split) - n_chairs} of {len(split)} samples scored" in captured.out
