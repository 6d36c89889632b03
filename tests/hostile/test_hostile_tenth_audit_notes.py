"""The tenth hostile audit's small notes (H8): messages that named the wrong problem, inputs
accepted in silence (a ``--val-data`` without val shapes, a KITTI car far from its box, a
prediction record's counts of 10^100), a PCN shape that stopped a whole ``predict`` run, and
bounds the other readers had (the bytes a ``.npy`` spans, the points of a scored completion).
"""

from __future__ import annotations

import json
import os
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
from brute import write_pcd

from pfnet.cli import main
from pfnet.data import load_split
from pfnet.data.benchmarks import load_partials, prepare_benchmark
from pfnet.data.kitti import kitti_input
from pfnet.errors import ConfigError, DataError
from pfnet.evaluation.benchmarks import evaluate_benchmark
from pfnet.evaluation.prediction_record import recorded_protocol
from pfnet.evaluation.protocols import shapenet_crop
from pfnet.evaluation.scoring import MAX_SCORED_POINTS
from pfnet.io.clouds import read_point_cloud
from pfnet.io.formats import MAX_BODY_BYTES

# corners 0 and 3 span the car's length (4 along x), PoinTr's order
BOX = np.array(
    [[2, 1, 0], [2, -1, 0], [2, -1, 1.5], [-2, 1, 0], [2, 1, 1.5], [-2, -1, 0], [-2, -1, 1.5]]
    + [[-2, 1, 1.5]],
    np.float64,
)


def _kitti_tree(root: Path, cars: dict[str, tuple[np.ndarray, np.ndarray]]) -> Path:
    for name, (points, box) in cars.items():
        write_pcd(root / "cars" / f"{name}.pcd", points)
        (root / "bboxes").mkdir(parents=True, exist_ok=True)
        np.savetxt(root / "bboxes" / f"{name}.txt", box)
    return root


def _pcn_tree(root: Path, shapes: dict[str, tuple[np.ndarray, np.ndarray]]) -> Path:
    for model, (complete, partial) in shapes.items():
        write_pcd(root / "test" / "complete" / "02691156" / f"{model}.pcd", complete)
        write_pcd(root / "test" / "partial" / "02691156" / model / "00.pcd", partial)
    record = {"taxonomy_id": "02691156", "taxonomy_name": "airplane", "test": list(shapes)}
    (root / "PCN.json").write_text(json.dumps([record]))
    return root


def _shape(seed: int) -> tuple[np.ndarray, np.ndarray]:
    cloud = np.random.default_rng(seed).normal(size=(16384, 3)).astype(np.float32)
    return cloud, cloud[cloud[:, 0] > 0][:600]


def test_readme_that_is_a_pipe_is_not_a_regular_file(tmp_path, capsys):
    fifo = tmp_path / "README.md"
    os.mkfifo(fifo)
    args = ["reproduce", "--out", str(tmp_path / "o"), "--report-only"]
    assert main([*args, "--readme", str(fifo)]) == 1
    assert f"--readme {fifo} is not a regular file" in capsys.readouterr().err
    assert main([*args, "--readme", str(tmp_path / "none.md")]) == 1
    assert "none.md does not exist" in capsys.readouterr().err


def test_train_refuses_val_data_without_val_shapes_and_a_kitti_data_set(
    tiny_dataset, tmp_path, capsys
):
    pytest.importorskip("torch")
    no_val = tmp_path / "no_val"
    shutil.copytree(tiny_dataset, no_val)
    empty = np.zeros(0, "<U1")
    np.savez(
        no_val / "val.npz", points=np.zeros((0, 512, 3), np.float32), category=empty, name=empty
    )
    manifest = json.loads((no_val / "manifest.json").read_text())
    manifest["splits"]["val"] = {"total": 0, "categories": {}}
    (no_val / "manifest.json").write_text(json.dumps(manifest))
    args = ["train", "--preset", "small", "--epochs", "1", "--device", "cpu"]
    run = tmp_path / "run"
    own = ["--data", str(tiny_dataset), "--out", str(run)]
    assert main([*args, *own, "--val-data", str(no_val)]) == 1
    assert (
        f"the validation data set {no_val} has no shapes in its val split"
        in capsys.readouterr().err
    )
    assert not (run / "last.pt").exists()
    car = np.random.default_rng(0).uniform([-2, -1, 0], [2, 1, 1.5], (300, 3))
    kitti = tmp_path / "kitti"
    prepare_benchmark(_kitti_tree(tmp_path / "KITTI", {"c0": (car, BOX)}), kitti, "kitti")
    assert main([*args, "--data", str(kitti), "--out", str(tmp_path / "run2")]) == 1
    err = capsys.readouterr().err
    assert f"{kitti} holds no complete clouds (a KITTI data set: for predict and evaluate" in err
    assert "removes 0 of 0 points" not in err


def test_kitti_prepare_skips_and_names_a_car_far_from_its_box(tmp_path):
    car = np.random.default_rng(0).uniform([-2, -1, 0], [2, 1, 1.5], (300, 3))
    tiny = BOX * 1e-6
    source = _kitti_tree(
        tmp_path / "KITTI",
        {
            "near": (car, BOX),
            "far": (car + 1e15, BOX),
            "tiny": (car, tiny),
            "edge": (car + [8, 0, 0], BOX),
        },
    )
    report = prepare_benchmark(source, tmp_path / "d", "kitti")
    reasons = dict(report.skipped)
    for name in ("far", "tiny"):
        why = reasons[str(source / "cars" / f"{name}.pcd")]
        assert f"no point within 3 box lengths of the centre of its box {name}.txt" in why
    assert report.counts["test"] == {"car": 2}  # near, and edge: 1.5 to 2.5 lengths away


def test_kitti_input_and_shapenet_crop_refuse_nan_points_and_a_bad_view():
    points = np.random.default_rng(0).normal(size=(4096, 3)).astype(np.float32)
    nan = points.copy()
    nan[7, 1] = np.nan
    with pytest.raises(DataError, match="car 0: points must be finite; some coordinates are NaN"):
        kitti_input(nan, BOX, "car 0")
    with pytest.raises(DataError, match="points must be finite: some coordinates are NaN"):
        shapenet_crop(nan, 0.25, 0)
    with pytest.raises(
        DataError, match=r"must have shape \(N, 3\) or \(B, N, 3\), got \(4096, 2\)"
    ):
        shapenet_crop(points[:, :2], 0.25, 0)
    for view in (True, 1.5, np.array([1, 2]), 8):
        with pytest.raises(ConfigError, match=r"view must be an integer in \[0, 8\), got"):
            shapenet_crop(points, 0.25, view)
    assert shapenet_crop(points, 0.25, np.int64(3)).shape == (2048, 3)


def test_pcn_prepare_refuses_degenerate_shapes_and_predict_skips_them(tmp_path, capsys):
    torch = pytest.importorskip("torch")
    from pfnet.inference.checkpoint import save_checkpoint
    from pfnet.models import build_model
    from pfnet.training.config import preset_config

    shapes = {f"m{k}": _shape(k) for k in range(3)}
    shapes["zeros"] = (np.zeros((16384, 3)), _shape(5)[1])
    shapes["one"] = (_shape(6)[0], np.ones((1, 3)))
    shapes["same"] = (_shape(7)[0], np.ones((500, 3)))
    source = _pcn_tree(tmp_path / "PCN", shapes)
    data = tmp_path / "data"
    report = prepare_benchmark(source, data, "pcn")
    reasons = dict(report.skipped)
    complete = source / "test" / "complete" / "02691156"
    assert "all 16384 points of the complete cloud coincide" in reasons[str(complete / "zeros.pcd")]
    for name, n in (("one", 1), ("same", 500)):
        assert (
            f"all {n} points of the partial scan coincide" in reasons[str(complete / f"{name}.pcd")]
        )
    assert report.counts["test"] == {"airplane": 3}
    # a data set forged (or prepared by an older pfnet) with a degenerate scan: skipped, named
    test = load_split(data, "test")
    scans = load_partials(data, "test", len(test))
    scans[1] = np.full_like(scans[1], 0.5)
    offsets = np.cumsum([0, *map(len, scans)])
    np.savez(data / "test.partial.npz", points=np.concatenate(scans), offsets=offsets)
    config = preset_config("small").replace(n_points=512, width=0.125)
    torch.manual_seed(0)
    checkpoint = tmp_path / "m.pt"
    save_checkpoint(
        checkpoint, {"config": config.to_dict(), "model": build_model(config).state_dict()}
    )
    out = tmp_path / "pred"
    args = ["predict", "--checkpoint", str(checkpoint), "--data", str(data), "--out", str(out)]
    assert main([*args, "--protocol", "pcn", "--device", "cpu"]) == 2
    captured = capsys.readouterr()
    bad = f"airplane/{test.name[1]}"
    assert f"skipped: {bad} (partial scan): all {len(scans[1])} points coincide" in captured.err
    assert "1 shape(s) could not be completed" in captured.err
    assert "wrote 2 completions" in captured.out
    assert sorted(p.stem for p in (out / "airplane").iterdir()) == [test.name[0], test.name[2]]
    record = json.loads((out / "predictions.json").read_text())
    assert record["complete"] and record["n_skipped"] == 1 and bad in record["skipped"][0]
    # the files it wrote: the skipped shape's is not among them
    want = {"endings": [".npy"], "names": {"airplane": sorted([test.name[0], test.name[2]])}}
    assert record["files"] == want
    # evaluate lists the skipped shape as missing and scores the rest
    evaluation = evaluate_benchmark(out, data, "pcn")
    assert evaluation.missing == [bad] and len(evaluation.categories) == 2
    # a completion of more than MAX_SCORED_POINTS points is named and not scored
    huge = np.random.default_rng(1).normal(size=(MAX_SCORED_POINTS + 1, 3)).astype(np.float32)
    np.save(out / "airplane" / f"{test.name[0]}.npy", huge)
    evaluation = evaluate_benchmark(out, data, "pcn")
    assert evaluation.unreadable == [f"airplane/{test.name[0]}"]
    assert (
        f"a completion of {MAX_SCORED_POINTS + 1} points; at most 131,072" in evaluation.reasons[0]
    )
    assert len(evaluation.categories) == 1


@pytest.mark.parametrize(
    ("where", "value", "want"),
    [
        (
            "n_points",
            10**100,
            r'"protocol.n_points" must be a positive integer of at most 50000000',
        ),
        (
            "views",
            10**12,
            r'"protocol.views" must be a positive integer of at most 8, got 1000000000000',
        ),
        ("views", 0, r'"protocol.views" must be a positive integer of at most 8, got 0'),
        ("views", "8", r'"protocol.views" must be a positive integer'),
    ],
)
def test_a_records_informational_counts_are_bounded(tmp_path, where, value, want):
    protocol = {"name": "shapenet55", "missing_ratio": 0.25, "n_points": 8192, "views": 8}
    protocol[where] = value
    record = {"complete": True, "split": "test", "protocol": protocol}
    (tmp_path / "predictions.json").write_text(json.dumps(record))
    with pytest.raises(DataError, match=want):
        recorded_protocol(tmp_path)


def test_npy_rows_are_bounded_by_the_bytes_they_span(tmp_path):
    rows = MAX_BODY_BYTES // 64 + 1  # 16 float32 columns: just over the bound
    header = f"{{'descr': '<f4', 'fortran_order': False, 'shape': ({rows}, 16), }}"
    header += " " * (-(10 + len(header) + 1) % 64) + "\n"
    file = tmp_path / "wide.npy"
    with open(file, "wb") as fh:
        fh.write(b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header.encode())
        fh.truncate(fh.tell() + rows * 64)
    with pytest.raises(DataError, match=rf"the \.npy rows \({rows}, 16\) span {rows * 64} bytes"):
        read_point_cloud(file)
    small = tmp_path / "ok.npy"
    np.save(small, np.ones((1000, 16), np.float32))
    assert read_point_cloud(small).shape == (1000, 3)


@pytest.mark.parametrize(("version", "length"), [(b"\x01\x00", 65_535), (b"\x02\x00", 2**32 - 1)])
def test_npy_header_lengths_beyond_the_file_are_refused_before_reading(tmp_path, version, length):
    """Audit 11 (N7): numpy read the header's declared length at once: 4 GiB from 20 bytes."""
    import struct

    from pfnet.errors import DataError
    from pfnet.io.clouds import read_point_cloud

    forged = tmp_path / "forged.npy"
    size = "<H" if version == b"\x01\x00" else "<I"
    forged.write_bytes(b"\x93NUMPY" + version + struct.pack(size, length) + b"{'descr'")
    with pytest.raises(DataError, match=f"its header claims {length} bytes, the file holds 8"):
        read_point_cloud(forged)
