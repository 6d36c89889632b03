"""benchmarks/run_curves.py: the validation level it draws, and the picture it writes."""

from __future__ import annotations

import json
from pathlib import Path

from scripts import load_script


def test_the_running_median_takes_the_window_before_each_epoch() -> None:
    script = load_script("run_curves")
    values = [10.0, 50.0, 20.0, 30.0, 5.0]
    assert script.running_median(values, window=3) == [10.0, 30.0, 20.0, 30.0, 20.0]
    assert script.running_median([], window=3) == []


def test_curves_of_two_runs_are_drawn(tmp_path: Path) -> None:
    script = load_script("run_curves")
    runs = []
    for name, offset in (("a", 0.0), ("b", 5.0)):
        run = tmp_path / name
        run.mkdir()
        rows = [{"epoch": 0, "val_cd_l2": 90.0 + offset}]
        rows += [
            {"epoch": e, "step": 36 * e, "cd_detail": 3.0 / e, "val_cd_l2": 40.0 / e + offset}
            for e in range(1, 15)
        ]
        text = "\n".join(json.dumps(r) for r in rows) + '\n{"epoch": 15, "st'  # a cut row
        (run / "log.jsonl").write_text(text, encoding="utf-8")
        runs.append(run)
    assert len(script.read_log(runs[0])) == 15
    out = tmp_path / "curves.png"
    assert script.main([*map(str, runs), "--out", str(out), "--label", "A", "--label", "B"]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
