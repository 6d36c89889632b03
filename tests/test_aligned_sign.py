"""benchmarks/aligned_sign.py: how often each sign rule of the aligned frame points at the hole."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scripts import load_script

script = load_script("aligned_sign")


def test_the_rules_point_to_the_farther_and_the_sparser_end() -> None:
    x = np.array([-1.0, -0.9, -0.8, 0.0, 0.5, 2.0])  # reaches to 2, three points at -1 end
    assert script.rule_signs(x, 0.3) == {
        "third moment": 1.0,
        "farther reach": 1.0,
        "sparser end": 1.0,
        "rim": 1.0,
    }
    assert script.rule_signs(-x, -0.3) == {
        "third moment": 1.0,
        "farther reach": -1.0,
        "sparser end": -1.0,
        "rim": -1.0,
    }


def test_agreement_counts_the_cuts_whose_hole_is_on_the_rules_side() -> None:
    rows = [
        {
            "hole": 1.0,
            "along": 0.9,
            "third moment": 1.0,
            "farther reach": -1.0,
            "sparser end": 1.0,
            "rim": 1.0,
        },
        {
            "hole": -1.0,
            "along": 0.9,
            "third moment": 1.0,
            "farther reach": -1.0,
            "sparser end": 1.0,
            "rim": 1.0,
        },
        {
            "hole": -1.0,
            "along": 0.1,
            "third moment": 1.0,
            "farther reach": -1.0,
            "sparser end": -1.0,
            "rim": -1.0,
        },
    ]
    table = script.agreement(rows, np.array(["a", "a", "b"]))
    assert table["cuts"] == 3 and table["along_the_main_axis"] == 2
    assert table["third moment"]["all"] == pytest.approx(1 / 3)
    assert table["third moment"]["along"] == pytest.approx(1 / 2)
    assert table["farther reach"]["all"] == pytest.approx(2 / 3)
    assert table["sparser end"]["categories"] == {"a": 0.5, "b": 1.0}


def test_a_bar_cut_at_one_end_has_its_hole_on_the_sparser_side(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    bar = rng.uniform([-1, -0.1, -0.1], [1, 0.1, 0.1], size=(512, 3))
    feet = rng.normal([-0.9, -0.1, 0.0], 0.02, size=(128, 3))  # a dense foot at the -x end
    cloud = np.concatenate([bar, feet, feet * [-1, 1, 1]]).astype(np.float32)  # and at +x
    # the first test viewpoint cuts one end away: the hole's end keeps fewer points
    rows = script.cut_rows(cloud[None], ratio=0.25)
    assert rows[0]["along"] > script.ALONG
    assert rows[0]["sparser end"] == rows[0]["hole"]


def test_the_script_writes_every_cut_of_a_split(tiny_dataset: Path, tmp_path: Path) -> None:
    out = tmp_path / "sign.json"
    document = script.main(["--data", str(tiny_dataset), "--split", "test", "--json", str(out)])
    assert json.loads(out.read_text()) == document
    assert document["cuts"] == 5 * 12 and document["views"] == 5
    for rule in script.RULES:
        assert 0.0 <= document[rule]["all"] <= 1.0
