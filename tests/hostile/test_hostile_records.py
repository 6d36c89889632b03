"""The eighth hostile audit's small findings: recorded JSON of loose types (a folder as
``predictions.json``, ``"false"`` as a boolean, ``true`` as a version, ``"512"`` as a count),
and messages that named the wrong thing or nothing (a folder called an unsupported suffix, a
full disk that named no file, an ``OverflowError`` from a geometry call)."""

from __future__ import annotations

import errno
import json
import math
import shutil
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
from forge import write_predictions

from pfnet import geometry
from pfnet.cli import main
from pfnet.errors import DataError, GeometryError
from pfnet.io.clouds import read_point_cloud
from pfnet.io.files import atomic_path


def _one_line(capsys, *parts: str) -> None:
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    for part in parts:
        assert part in err, err


GOOD_RECORD = {
    "complete": True,
    "split": "test",
    "protocol": {"name": "test", "missing_ratio": 0.25, "n_points": 512},
    "model": {"name": "pfnet", "n_points": 512},
}


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"complete": "false"}, '"complete" must be true or false, got "false"'),
        ({"split": ["test"]}, '"split" must be a split\'s name'),
        ({"protocol": "test"}, '"protocol" must be an object'),
        ({"protocol": {"missing_ratio": "0.25"}}, '"protocol.missing_ratio" must be a number'),
        ({"protocol": {"missing_ratio": True}}, '"protocol.missing_ratio" must be a number'),
        ({"protocol": {"missing_ratio": math.nan}}, "got nan"),  # not blamed on --missing-ratio
        ({"protocol": {"missing_ratio": 0.25, "n_points": True}}, '"protocol.n_points" must be'),
        ({"protocol": {"missing_ratio": 0.25, "n_points": -1}}, '"protocol.n_points" must be'),
        ({"model": [1]}, '"model" must be an object'),
        ({"model": {"n_points": "512"}}, '"model.n_points" must be a positive integer'),
        ({"model": {"n_points": 600}}, "trained on clouds of 600 points but predicted clouds of"),
        # the ninth audit: neither the file nor shapenet34 was named; a string count passed
        ({"protocol": {"name": "zzz"}}, '"protocol.name" must be one of test, pfnet, pcn'),
        ({"protocol": {"name": "zzz"}}, "shapenet34"),
        ({"model": {"n_predicted": "128"}}, '"model.n_predicted" must be a positive integer'),
    ],
)
def test_prediction_records_of_loose_types_are_refused(
    tmp_path: Path, tiny_dataset: Path, change: dict, message: str, capsys
) -> None:
    pred = write_predictions(tmp_path / "pred", tiny_dataset)
    (pred / "predictions.json").write_text(json.dumps({**GOOD_RECORD, **change}))
    assert main(["evaluate", str(pred), "--data", str(tiny_dataset)]) == 1
    _one_line(capsys, str(pred / "predictions.json"), message, "--ignore-recorded-protocol")


def test_a_folder_as_the_prediction_record_is_refused(
    tmp_path: Path, tiny_dataset: Path, capsys
) -> None:
    pred = write_predictions(tmp_path / "pred", tiny_dataset)
    (pred / "predictions.json").mkdir()  # was scored as if there were no record
    assert main(["evaluate", str(pred), "--data", str(tiny_dataset)]) == 1
    _one_line(capsys, str(pred / "predictions.json"), "not a file")
    (pred / "predictions.json").rmdir()
    (pred / "predictions.json").write_text(json.dumps(GOOD_RECORD))
    assert main(["evaluate", str(pred), "--data", str(tiny_dataset)]) == 0  # the good one scores
    capsys.readouterr()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"version": True}, "format version true is not supported"),
        ({"version": -7}, "format version -7 is not supported"),
        ({"version": 1.0}, "format version 1.0 is not supported"),
        ({"points": "512"}, 'points per cloud must be a positive integer, got "512"'),
        ({"points": -1}, "points per cloud must be a positive integer, got -1"),
        ({"points": True}, "points per cloud must be a positive integer, got true"),
    ],
)
def test_manifests_of_loose_types_are_refused(
    tmp_path: Path, tiny_dataset: Path, change: dict, message: str, capsys
) -> None:
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    manifest = json.loads((data / "manifest.json").read_text())
    (data / "manifest.json").write_text(json.dumps({**manifest, **change}))
    pred = write_predictions(tmp_path / "pred", tiny_dataset)
    assert main(["evaluate", str(pred), "--data", str(data)]) == 1
    _one_line(capsys, str(data / "manifest.json"), message)


def test_a_folder_given_to_complete_is_called_a_folder(tmp_path: Path) -> None:
    (tmp_path / "scans").mkdir()
    with pytest.raises(DataError, match="scans: a folder, not a point cloud file"):
        read_point_cloud(tmp_path / "scans")


def test_a_full_disk_names_the_file_being_written(tmp_path: Path) -> None:
    from pfnet.data.format import CloudSet, write_dataset

    target = tmp_path / "report.json"
    with pytest.raises(OSError) as caught, atomic_path(target) as tmp:
        tmp.write_text("{")
        raise OSError(errno.ENOSPC, "No space left on device")  # as a write() gives it
    assert caught.value.filename == str(target)
    assert list(tmp_path.iterdir()) == []  # the temporary file is gone

    def full(*_args, **_kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    empty = CloudSet(np.zeros((0, 8, 3), np.float32), np.array([], "U1"), np.array([], "U1"))
    splits = dict.fromkeys(("train", "val", "test"), empty)
    with pytest.MonkeyPatch.context() as patch, pytest.raises(OSError) as caught:
        patch.setattr("pfnet.data.format.write_npz", full)
        write_dataset(tmp_path / "data", splits, {})
    assert caught.value.filename == str(tmp_path / "data")


@pytest.mark.parametrize("radius", [10**400, Fraction(10**400)])
def test_a_radius_beyond_float64_is_a_geometry_error(radius) -> None:
    cloud = np.random.default_rng(0).random((10, 3), dtype=np.float32)
    with pytest.raises(GeometryError, match="radius must be a finite number"):
        geometry.crop_by_viewpoint(cloud, [0.0, 0.0, 1.0], radius=radius)
    with pytest.raises(GeometryError, match="viewpoint must be finite"):
        geometry.crop_by_viewpoint(cloud, [10**400, 0, 1], radius=1.0)


def test_float64_beyond_float32_is_refused_without_numpys_warning() -> None:
    # pytest turns warnings into errors here: the core's message must come alone
    with pytest.raises(GeometryError, match="NaN or infinite"):
        geometry.farthest_point_sample(np.full((5, 3), 1e39), 2)
