"""benchmarks/hold_out.py: a data set without another one's val and test shapes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scripts import load_script

from pfnet.data.format import (
    FORMAT_NAME,
    FORMAT_VERSION,
    SPLITS,
    CloudSet,
    load_split,
    split_record,
    write_dataset,
)


def _data_set(root: Path, names: dict[str, list[str]], pool: bool) -> Path:
    rng = np.random.default_rng(len(str(root)))
    splits = {}
    for split in SPLITS:
        n = len(names[split])
        points = rng.normal(size=(n, 16, 3)).astype(np.float32)
        extra = rng.normal(size=(n, 8, 3)).astype(np.float32) if pool else None
        splits[split] = CloudSet(points, np.array(["chair"] * n), np.array(names[split]), extra)
    manifest = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "points": 16,
        "categories": ["chair"],
        "splits": {split: split_record(clouds) for split, clouds in splits.items()},
    }
    return write_dataset(root, splits, manifest)


def test_the_held_out_shapes_leave_train_and_val_and_the_rest_is_kept(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    big = _data_set(
        tmp_path / "big",
        {"train": ["a", "b", "c", "d"], "val": ["e", "f"], "test": ["g", "h"]},
        pool=True,
    )
    held = _data_set(
        tmp_path / "held", {"train": ["e"], "val": ["b"], "test": ["c", "g", "x"]}, pool=False
    )
    out = tmp_path / "out"
    assert load_script("hold_out").main([str(big), "--held", str(held), "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert "train: kept 2, left out 2" in said and "val: kept 2, left out 0" in said
    train = load_split(out, "train")
    assert train.name.tolist() == ["a", "d"]
    source = load_split(big, "train")
    np.testing.assert_array_equal(train.points, source.points[[0, 3]])
    np.testing.assert_array_equal(train.extra, source.extra[[0, 3]])
    # the held set's train shape 'e' stays in val; test stays whole ('g' is fair to score)
    assert load_split(out, "val").name.tolist() == ["e", "f"]
    assert load_split(out, "test").name.tolist() == ["g", "h"]
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["held_out"]["left_out"] == {"train": ["b", "c"], "val": [], "test": []}
