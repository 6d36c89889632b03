"""Hostile text files: `.xyz` and ASCII PLY are read a block of lines at a time, so memory
follows the points a file holds, not its lines; an overlong line is refused by number; the
lines after a PLY's vertices are never read (the sixth audit: a 60 MB tail of twenty million
short lines took 2.2 GB, one 400-million-token line 5.2 GB)."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from pfnet.errors import DataError
from pfnet.io.clouds import read_point_cloud
from pfnet.io.formats.lines import MAX_LINE_BYTES

PLY_HEADER = (
    "ply\nformat ascii 1.0\nelement vertex {n}\n"
    "property float x\nproperty float y\nproperty float z\nend_header\n"
)


def test_an_overlong_line_is_refused_by_number(tmp_path: Path) -> None:
    long = "1 " * (MAX_LINE_BYTES // 2 + 10) + "\n"
    xyz = tmp_path / "long.xyz"
    xyz.write_text("0 0 0\n1 1 1\n" + long)
    with pytest.raises(DataError, match=r"long\.xyz: line 3 is longer than 65536 bytes"):
        read_point_cloud(xyz)
    ply = tmp_path / "long.ply"
    ply.write_text(PLY_HEADER.format(n=2) + "0 0 0\n" + long)
    with pytest.raises(DataError, match=r"long\.ply: line 9 is longer than"):  # file lines
        read_point_cloud(ply)


def test_lines_after_the_ply_vertices_are_not_read(tmp_path: Path) -> None:
    ply = tmp_path / "tail.ply"
    tail = "12\n" * 100_000 + "x" * (4 * MAX_LINE_BYTES) + "\n\xff\xfe not text"
    ply.write_text(PLY_HEADER.format(n=3) + "1 2 3\n4 5 6\n7 8 9\n" + tail, encoding="latin-1")
    np.testing.assert_array_equal(read_point_cloud(ply), [[1, 2, 3], [4, 5, 6], [7, 8, 9]])


def test_an_ascii_ply_claiming_more_vertices_than_it_has_is_truncated(tmp_path: Path) -> None:
    ply = tmp_path / "short.ply"
    ply.write_text(PLY_HEADER.format(n=19_000_000) + "1 2 3\n4 5 6\n")
    tracemalloc.start()
    try:
        with pytest.raises(DataError, match="truncated PLY data"):
            read_point_cloud(ply)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 50e6  # nothing of the claimed 19 million rows was allocated


@pytest.mark.slow  # end to end, or a measurement: runs in CI, not the default run
@pytest.mark.parametrize("kind", ["xyz", "ply"])
def test_text_readers_use_memory_in_proportion_to_the_points(tmp_path: Path, kind: str) -> None:
    n = 300_000
    rows = "12 34 56\n" * n
    path = tmp_path / f"many.{kind}"
    path.write_text((PLY_HEADER.format(n=n) if kind == "ply" else "") + rows)
    tracemalloc.start()
    try:
        points = read_point_cloud(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert points.shape == (n, 3)
    # about 60 bytes a point now (float64 blocks, their join, the float32 result); reading
    # the lines as Python strings took 360
    assert peak < 100 * n, f"{peak / n:.0f} bytes a point"


def test_text_points_with_uneven_columns_and_comments_still_read(tmp_path: Path) -> None:
    path = tmp_path / "mixed.xyz"
    path.write_text(
        "\ufeffx,y,z\n# comment\n0,0,0\n1 1 1 0.5 0.5 0.5\n\n// note\n2\t2\t2 # after\n3, 3, 3\n"
    )
    np.testing.assert_array_equal(
        read_point_cloud(path), [[0, 0, 0], [1, 1, 1], [2, 2, 2], [3, 3, 3]]
    )
    bad = tmp_path / "bad.xyz"
    bad.write_text("0 0 0\n" * 70_000 + "1 1_0 1\n")  # the bad line in the second block
    with pytest.raises(DataError, match=r"line 70001 is not numeric: '1 1_0 1'"):
        read_point_cloud(bad)
    count = tmp_path / "count.pts"
    count.write_text("7\n")
    with pytest.raises(DataError, match="line 1 has 1 column"):
        read_point_cloud(count)


def test_a_split_member_numpy_would_prefer_is_refused(tmp_path: Path, tiny_dataset: Path) -> None:
    """The seventh audit: numpy reads a member named "points" before "points.npy", so a
    member without the suffix escaped every size check (598 kB → 1.2 GB)."""
    import shutil
    import zipfile

    from pfnet.data import load_split

    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    with zipfile.ZipFile(data / "test.npz", "a") as archive:
        archive.writestr("points", b"\x93NUMPY forged")
    with pytest.raises(DataError, match=r"test.npz: unexpected member 'points' \(a split holds"):
        load_split(data, "test")


def test_reports_replace_no_device_or_pipe_nor_write_through_links(
    tmp_path: Path, tiny_dataset: Path
) -> None:
    import os

    from forge import write_predictions

    from pfnet.cli import main

    pred = write_predictions(tmp_path / "pred", tiny_dataset)
    pipe = tmp_path / "pipe"
    os.mkfifo(pipe)
    link = tmp_path / "link.json"
    link.symlink_to(tmp_path / "elsewhere.json")
    for target in (pipe, Path("/dev/null")):
        code = main(["evaluate", str(pred), "--data", str(tiny_dataset), "--json", str(target)])
        assert code == 1
    assert pipe.is_fifo() and Path("/dev/null").is_char_device()
    # a link is replaced by the report, never written through
    assert main(["evaluate", str(pred), "--data", str(tiny_dataset), "--json", str(link)]) == 0
    assert not link.is_symlink() and not (tmp_path / "elsewhere.json").exists()


def test_binary_bodies_are_mapped_not_read_and_headers_bounded(tmp_path: Path) -> None:
    from pfnet.io.clouds import write_ply

    path = tmp_path / "padded.ply"
    write_ply(path, np.arange(30, dtype=np.float32).reshape(10, 3))
    with open(path, "r+b") as fh:  # a sparse gigabyte after the points: no disk, no memory
        fh.truncate(path.stat().st_size + 2**30)
    tracemalloc.start()
    try:
        assert read_point_cloud(path).shape == (10, 3)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 10e6
    header = tmp_path / "header.ply"
    header.write_bytes(b"ply\nformat ascii 1.0\ncomment " + b"x" * (2 * MAX_LINE_BYTES))
    with pytest.raises(DataError, match="header line 2 is longer than"):
        read_point_cloud(header)


def test_ascii_pcd_is_read_in_blocks_and_a_compression_bomb_refused(tmp_path: Path) -> None:
    import struct

    head = "VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\n"
    pcd = tmp_path / "tail.pcd"
    pcd.write_text(head.format(n=3) + "POINTS 3\nDATA ascii\n1 2 3\n4 5 6 7\n7 8 9\n" + "x\n" * 99)
    np.testing.assert_array_equal(read_point_cloud(pcd), [[1, 2, 3], [4, 5, 6], [7, 8, 9]])
    n = 20_000_000  # 240 MB declared in a few bytes
    bomb = tmp_path / "bomb.pcd"
    body = struct.pack("<II", 100, 12 * n) + bytes(100)
    bomb.write_bytes((head.format(n=n) + f"POINTS {n}\nDATA binary_compressed\n").encode() + body)
    with pytest.raises(DataError, match="claims to expand 2400000 times"):
        read_point_cloud(bomb)


def test_evaluate_refuses_predictions_of_clouds_of_another_size(
    tmp_path: Path, tiny_dataset: Path, capsys
) -> None:
    """The seventh audit: 512-point predictions scored against 2,048-point clouds, rc 0."""
    import json

    from forge import write_predictions

    from pfnet.cli import main

    pred = write_predictions(tmp_path / "pred", tiny_dataset, record=True)
    info = json.loads((pred / "predictions.json").read_text())
    info["protocol"]["n_points"] = 2048  # the data set's clouds have 512
    (pred / "predictions.json").write_text(json.dumps(info))
    base = ["evaluate", str(pred), "--data", str(tiny_dataset)]
    assert main(base) == 1
    err = capsys.readouterr().err
    assert "was predicted from clouds of 2048 points" in err and "has 512" in err
    assert main([*base, "--ignore-recorded-protocol"]) == 0
    info["protocol"]["n_points"] = 512
    (pred / "predictions.json").write_text(json.dumps(info))
    assert main(base) == 0


def test_odd_dtypes_and_manifests_are_refused(tmp_path: Path, tiny_dataset: Path) -> None:
    import json
    import shutil

    from pfnet.data import load_split

    path = tmp_path / "t.npy"
    np.save(path, np.zeros((10, 3), "m8[s]"))  # timedelta64 is an integer to numpy
    with pytest.raises(DataError, match="expected numeric coordinates, got dtype timedelta64"):
        read_point_cloud(path)
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    manifest = json.loads((data / "manifest.json").read_text())
    (data / "manifest.json").write_text(json.dumps({**manifest, "categories": "x"}))
    with pytest.raises(DataError, match="categories must be a list of names"):
        load_split(data, "test")
    (data / "manifest.json").write_text(json.dumps(manifest) + " " * (17 << 20))
    with pytest.raises(DataError, match="larger than 16 MB; not a manifest"):
        load_split(data, "test")


def test_a_checkpoint_with_compressed_members_is_refused_before_loading(tmp_path: Path) -> None:
    """The seventh audit: torch.load unpacked a deflated 1.2 GB tensor of a 5.6 MB file."""
    import zipfile

    torch = pytest.importorskip("torch")
    from pfnet.inference.checkpoint import read_checkpoint

    path = tmp_path / "c.pt"
    torch.save({"format": "x", "junk": torch.zeros(10)}, path)
    with zipfile.ZipFile(path) as archive:
        members = [(i, archive.read(i)) for i in archive.infolist()]
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        for info, data in members:
            archive.writestr(info.filename, data)
    with pytest.raises(DataError, match="has compressed members .* torch.save never writes"):
        read_checkpoint(path)


def test_an_interrupted_predict_leaves_a_record_evaluate_refuses(
    tmp_path: Path, tiny_dataset: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    """The seventh audit: Ctrl-C while predict rewrote a folder left new files, old files and
    the old record, and evaluate scored the mix."""
    pytest.importorskip("torch")
    from forge import write_predictions

    from pfnet.cli import main
    from pfnet.io import clouds as pfnet_io

    out = tmp_path / "pred"
    base = ["predict", "--data", str(tiny_dataset), "--out", str(out), "--device", "cpu"]

    write_predictions(out, tiny_dataset, record=True)  # an earlier, complete run
    written = []

    def interrupted(path, array):
        written.append(path)
        if len(written) == 3:
            raise KeyboardInterrupt
        np.save(path, array)

    monkeypatch.setattr(pfnet_io, "save_npy", interrupted)
    ckpt = _tiny_checkpoint(tmp_path, tiny_dataset)
    assert main([*base, "--checkpoint", str(ckpt), "--missing-ratio", "0.5"]) == 130
    capsys.readouterr()
    assert main(["evaluate", str(out), "--data", str(tiny_dataset)]) == 1
    assert "stopped before writing every file" in capsys.readouterr().err
    monkeypatch.undo()
    assert main([*base, "--checkpoint", str(ckpt), "--missing-ratio", "0.5"]) == 0
    capsys.readouterr()
    assert main(["evaluate", str(out), "--data", str(tiny_dataset)]) == 0


def _tiny_checkpoint(tmp_path: Path, data: Path) -> Path:
    import torch

    from pfnet.data import load_split
    from pfnet.inference.checkpoint import save_checkpoint
    from pfnet.models import build_model
    from pfnet.training import preset_config

    n_points = load_split(data, "test").points.shape[1]
    config = preset_config("small").replace(model="mlp", width=0.125, n_points=n_points)
    torch.manual_seed(0)
    path = tmp_path / "model.pt"
    save_checkpoint(path, {"config": config.to_dict(), "model": build_model(config).state_dict()})
    return path


def test_names_are_bounded_in_bytes_not_only_characters() -> None:
    """A 200-character name of 600 bytes made predict fail with "File name too long" after
    it had replaced some files."""
    from pfnet.data import CloudSet

    points = np.zeros((1, 8, 3), np.float32)
    with pytest.raises(DataError, match="is longer than 200 bytes in UTF-8"):
        CloudSet(points, np.array(["chair"]), np.array(["\u20ac" * 100]))
    assert len(CloudSet(points, np.array(["chair"]), np.array(["e" * 200]))) == 1


def test_f_score_thresholds_must_be_distances() -> None:
    from pfnet.errors import ConfigError
    from pfnet.evaluation.metrics import sample_metrics

    clouds = np.random.default_rng(0).random((2, 50, 3)).astype(np.float32)
    for bad in (-1.0, float("nan"), 0.0, float("inf")):
        with pytest.raises(ConfigError, match="f_threshold must be a positive finite distance"):
            sample_metrics(clouds, clouds, f_threshold=bad)
    assert sample_metrics(clouds, clouds)["f_score"].tolist() == [1.0, 1.0]
