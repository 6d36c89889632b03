"""Hostile files: readers check the sizes a file declares against the bytes it has before they
allocate or loop, and every command turns a bad file into one line naming it."""

from __future__ import annotations

import contextlib
import errno
import io
import os
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
from pfnet.io.clouds import read_point_cloud, write_ply


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
    with (
        _deadline(30),
        pytest.raises(
            DataError, match="forged.ply: (truncated|negative|PLY element .face. brings)"
        ),
    ):
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


def _deflated_split(path: Path, rows: int, points: int, name_rows: int | None = None) -> None:
    """A split of ``rows`` all-zero clouds, deflated (it compresses about 1000 times)."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for member, array in (
            ("points", np.zeros((rows, points, 3), np.float32)),
            ("category", np.full(rows if name_rows is None else name_rows, "chair")),
            ("name", np.array([f"s{i}" for i in range(rows)])),
        ):
            with archive.open(f"{member}.npy", "w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, array)


def test_a_deflate_bomb_in_a_split_is_refused_even_with_a_forged_manifest(
    tmp_path: Path, tiny_dataset: Path
) -> None:
    """The sixth audit: a 1.2 MB test.npz expanded to 2.8 GB once its manifest row count was
    forged to agree; point coordinates cannot compress that far, whatever the manifest says."""
    import json
    import shutil

    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    rows = 2_000  # 12 MB of zeros, deflated to a few kB: the same ratio as the audit's bomb
    _deflated_split(data / "test.npz", rows, 512)
    manifest = json.loads((data / "manifest.json").read_text())
    manifest["splits"]["test"] = {"total": rows, "categories": {"chair": rows}}
    (data / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(DataError, match=r"points.npy claims to expand \d+ times; point coord"):
        load_split(data, "test")
    # without a manifest record, members must at least agree with one another
    del manifest["splits"]
    (data / "manifest.json").write_text(json.dumps(manifest))
    np.savez(
        data / "test.npz",
        points=np.ones((3, 512, 3), np.float32),
        category=np.full(300, "chair"),
        name=np.array(["a", "b", "c"]),
    )
    with pytest.raises(DataError, match=r"members hold different numbers of shapes"):
        load_split(data, "test")


def test_a_split_larger_than_the_free_memory_is_refused_before_loading(
    tmp_path: Path, tiny_dataset: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import shutil

    from pfnet.data import archives

    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    monkeypatch.setattr(archives, "available_memory", lambda: 10_000)
    with pytest.raises(
        DataError, match=r"test.npz: loading the split needs [\d.]+ MB of memory; 0.0 MB are"
    ):
        load_split(data, "test")
    monkeypatch.setattr(archives, "available_memory", lambda: None)  # not Linux: no check
    assert len(load_split(data, "test")) == 12


def test_one_bad_file_does_not_stop_a_complete_batch(tmp_path: Path, capsys) -> None:
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
    from pfnet.inference.checkpoint import FORMAT, VERSION, save_checkpoint
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
    import pfnet.evaluation.reports

    pred = write_predictions(tmp_path / "pred", tiny_dataset)

    def full_disk(*_args, **_kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "m.json"))

    monkeypatch.setattr(pfnet.evaluation.reports, "write_json", full_disk)
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


# ----------------------------------------------------------------------------------------
# The second audit's variants (a fresh hostile run against the fixes above).


def _ply(path: Path, header: str, body: bytes = b"") -> Path:
    path.write_bytes(("ply\n" + header + "end_header\n").encode() + body)
    return path


def _pcd(path: Path, fields: str, data: str, body: bytes) -> Path:
    path.write_bytes(("VERSION 0.7\n" + fields + f"DATA {data}\n").encode() + body)
    return path


def _sparse(path: Path, head: bytes, size: int) -> Path:
    path.write_bytes(head)
    os.truncate(path, size)  # zeros that take no disk
    return path


def _malformed_files(folder: Path) -> dict[str, tuple[Path, str]]:
    """Each file with the message its reading must give (none may parse)."""
    bin_le = "format binary_little_endian 1.0\n"
    xyz_float = "property float x\nproperty float y\nproperty float z\n"
    xyz3 = "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\n"
    return {
        "count0.pcd": (
            _pcd(
                folder / "count0.pcd",
                xyz3 + "COUNT 0 0 0\nPOINTS 1\n",
                "binary_compressed",
                struct.pack("<II", 0, 0),
            ),
            "COUNT below 1",
        ),
        "negative.pcd": (
            _pcd(
                folder / "negative.pcd",
                xyz3 + "COUNT 1 1 1\nPOINTS -5\n",
                "binary",
                np.zeros(30, "<f4").tobytes(),
            ),
            "negative point count",
        ),
        "countneg.pcd": (
            _pcd(folder / "countneg.pcd", xyz3 + "COUNT -2 1 1\nPOINTS 1\n", "ascii", b"1 2 3\n"),
            "COUNT below 1",
        ),
        "floatlen.ply": (
            _ply(
                folder / "floatlen.ply",
                bin_le + "element vertex 1\n" + xyz_float + "property list float uchar foo\n",
                np.zeros(4, "<f4").tobytes(),
            ),
            "list length type must be an integer",
        ),
        "twice.ply": (
            _ply(
                folder / "twice.ply",
                bin_le + "element vertex 1\n" + xyz_float + "property float x\n",
                np.zeros(4, "<f4").tobytes(),
            ),
            "declared twice",
        ),
        "digits.ply": (
            _ply(folder / "digits.ply", bin_le + f"element vertex {'9' * 5000}\n" + xyz_float),
            "malformed PLY element line",
        ),
        "negasc.ply": (
            _ply(
                folder / "negasc.ply",
                "format ascii 1.0\nelement vertex 1\n"
                + xyz_float
                + "property list uchar int ids\n",
                b"1 2 3 -3 7 8\n",
            ),
            "malformed PLY vertex line",
        ),
        "walk.ply": (
            _ply(
                folder / "walk.ply",
                bin_le + "element face 3000000\n"
                "property list uchar int ids\nelement vertex 1\n" + xyz_float,
                bytes(3_000_000) + np.zeros(3, "<f4").tobytes(),
            ),
            "list lengths to read before the vertices",
        ),
        # the eighth audit's: a gigabyte first line, COUNT 10^8, 10^8 honest vertices (sparse)
        "magic.ply": (_sparse(folder / "magic.ply", b"plyx", 2**30), "not a PLY file"),
        "values.pcd": (
            _pcd(
                folder / "values.pcd",
                "FIELDS x y z w\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 100000000\nPOINTS 1\n",
                "ascii",
                b"1 2 3 4\n",
            ),
            "declares 100000003 values a point",
        ),
        "many.ply": (
            _sparse(
                folder / "many.ply",
                f"ply\n{bin_le}element vertex 100000000\n{xyz_float}end_header\n".encode(),
                1_200_000_200,
            ),
            "declares 100000000 points; pfnet reads at most 50,000,000",
        ),
        "underscore.xyz": (folder / "underscore.xyz", "is not numeric"),
        "huge.xyz": (folder / "huge.xyz", "coordinates beyond"),
    }


def test_malformed_files_of_the_second_audit_are_named_errors(tmp_path: Path) -> None:
    files = _malformed_files(tmp_path)
    (tmp_path / "underscore.xyz").write_text("1_0 2 3\n4 5 6\n")
    (tmp_path / "huge.xyz").write_text("1e30 2 3\n4 5 6\n")
    for name, (path, message) in files.items():
        with _deadline(20), pytest.raises(DataError, match=message):
            read_point_cloud(path)
        assert name in str(path)


def test_complete_and_evaluate_go_on_past_every_malformed_file(
    tmp_path: Path, tiny_dataset: Path, capsys
) -> None:
    pytest.importorskip("torch")
    from pfnet.inference.checkpoint import save_checkpoint
    from pfnet.models import build_model
    from pfnet.training.config import preset_config

    config = preset_config("small").replace(n_points=512, width=0.125)
    checkpoint = tmp_path / "m.pt"
    save_checkpoint(
        checkpoint, {"config": config.to_dict(), "model": build_model(config).state_dict()}
    )
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "underscore.xyz").write_text("1_0 2 3\n4 5 6\n")
    (bad / "huge.xyz").write_text("1e30 2 3\n4 5 6\n")
    files = [path for path, _ in _malformed_files(bad).values()]
    good = tmp_path / "good.ply"
    write_ply(good, np.random.default_rng(0).normal(size=(400, 3)).astype(np.float32))
    args = ["complete", *map(str, files), str(good), "--out", str(tmp_path / "out")]
    with _deadline(60):
        assert main([*args, "--checkpoint", str(checkpoint), "--device", "cpu"]) == 2
    captured = capsys.readouterr()
    assert f"completed 1 of {len(files) + 1}" in captured.out
    assert all(path.name in captured.err for path in files) and "Traceback" not in captured.err

    # evaluate: one prediction far beyond the float32 range, one merely far away
    pred = write_predictions(tmp_path / "pred", tiny_dataset)
    victims = sorted(pred.rglob("*.npy"))[:2]
    np.save(victims[0], np.full((128, 3), 1e30, np.float32))
    np.save(victims[1], np.full((128, 3), 9e17, np.float32))
    assert main(["evaluate", str(pred), "--data", str(tiny_dataset)]) == 2
    captured = capsys.readouterr()
    assert "coordinates beyond" in captured.err and victims[0].stem in captured.err
    assert "reach more than 10 from the origin" in captured.err


def test_forged_model_configs_are_refused_before_building_anything(tmp_path: Path, capsys) -> None:
    pytest.importorskip("torch")
    from pfnet.inference.checkpoint import save_checkpoint
    from pfnet.training.config import preset_config

    config = preset_config("paper").replace(n_points=65536, width=4.0, missing_ratio=0.5)
    path = tmp_path / "forged.pt"
    save_checkpoint(path, {"config": config.to_dict(), "model": {}})
    scan = tmp_path / "scan.ply"
    write_ply(scan, np.random.default_rng(0).normal(size=(400, 3)).astype(np.float32))
    with _deadline(20):  # it used to build 1.2 billion parameters (5.3 GB, 18 s) first
        assert (
            main(["complete", str(scan), "--checkpoint", str(path), "--out", str(tmp_path / "o")])
            == 1
        )
    err = capsys.readouterr().err
    assert "does not match the model its config describes: missing" in err and "more" in err
    assert len(err.splitlines()) == 1 and len(err) < 600

    from safetensors.numpy import save_file

    deep = tmp_path / "deep.safetensors"
    meta = {"format": "pfnet-shipped-model", "version": "1", "config": "[" * 100000 + "]" * 100000}
    save_file({"w": np.zeros(1, np.float32)}, str(deep), metadata=meta)
    assert (
        main(["complete", str(scan), "--checkpoint", str(deep), "--out", str(tmp_path / "o")]) == 1
    )
    assert "has a broken header" in capsys.readouterr().err


def test_a_split_whose_clouds_disagree_with_the_manifest_is_refused(
    tmp_path: Path, tiny_dataset: Path, capsys
) -> None:
    import shutil

    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    test = load_split(data, "test")
    np.savez(data / "test.npz", points=test.points[:, :100], category=test.category, name=test.name)
    with pytest.raises(DataError, match=r"has clouds of shape \(100, 3\), not 512 points"):
        load_split(data, "test")
    pred = write_predictions(tmp_path / "pred", tiny_dataset)
    assert main(["evaluate", str(pred), "--data", str(tiny_dataset), "--workers", "100000"]) == 1
    assert "--workers must be in [1, 256]" in capsys.readouterr().err
