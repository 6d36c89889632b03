"""benchmarks/frame_hole.py: where each scan frame puts the hole."""

from __future__ import annotations

import json
from pathlib import Path

from scripts import load_script

script = load_script("frame_hole")


def test_the_script_scores_every_frame_on_every_cut(tiny_dataset: Path, tmp_path: Path) -> None:
    out = tmp_path / "hole.json"
    document = script.main(["--data", str(tiny_dataset), "--split", "test", "--json", str(out)])
    assert json.loads(out.read_text()) == document
    assert document["cuts"] == 5 * 12
    for frame in script.FRAMES:
        assert 0.0 <= document[frame]["on_plus_x"] <= 1.0
        assert -1.0 <= document[frame]["median_cosine"] <= 1.0
