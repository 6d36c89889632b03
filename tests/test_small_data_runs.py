"""benchmarks/small_data_runs.py: the rows of finished training runs."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from scripts import load_script


@pytest.fixture(scope="module")
def small_data_runs():
    return load_script("small_data_runs")


def _run(folder: Path, rows: list[dict]) -> Path:
    folder.mkdir()
    config = {"width": 0.25, "seed": 0, "loss_scale": 50.0, "chamfer": "l1"}
    (folder / "config.json").write_text(json.dumps(config))
    (folder / "log.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return folder


def test_a_run_with_a_weight_average_gets_a_row_for_its_live_weights(
    small_data_runs, tmp_path, capsys
):
    rows = [{"epoch": 0, "val_cd_l2": 99.0}]  # epoch 0 has no step: left out
    for step, (average, live) in enumerate([(9.0, 12.0), (8.0, 7.0), (7.5, 9.0)], start=1):
        validation = {"val_cd_l2": average, "val_f_score": 0.02}
        validation |= {"val_live_cd_l2": live, "val_live_f_score": 0.01}
        rows.append({"epoch": step, "step": step * 100, "cd_detail": 0.5, **validation})
    ema = _run(tmp_path / "ema", rows)
    plain = _run(
        tmp_path / "plain", [{k: v for k, v in r.items() if "live" not in k} for r in rows]
    )
    (ema / "eval-test-best.json").write_text(
        json.dumps({"mean": {"pred_to_gt": 4.0, "gt_to_pred": 3.5, "f_score": 0.03}})
    )
    scored, live = small_data_runs.summarise(ema), small_data_runs.summarise(ema, live=True)
    assert (scored["val_best"], scored["val_best_step"]) == (7.5, 300)
    assert (live["val_best"], live["val_best_step"]) == (7.0, 200)
    assert live["val_f_last_tenth"] == 0.01 and scored["val_f_last_tenth"] == 0.02
    assert scored["test_best"] == 7.5 and "test_best" not in live  # the test scored the average
    assert small_data_runs.main([str(ema), str(plain)]) == 0
    out = capsys.readouterr().out
    assert "| ema | l1 | 300 | 10.00 | 7.50 | 7.50 (step 300) | 0.020 | 7.50 | 0.030 |" in out
    assert (
        "| ema (live weights) | l1 | 300 | 10.00 | 9.00 | 7.00 (step 200) | 0.010 | — | — |" in out
    )
    assert "plain (live weights)" not in out


def _readme_row(label: str) -> str:
    """The row of the recipe page (docs/recipes.md) whose first cell is ``label``."""
    root = Path(__file__).resolve().parent.parent
    readme = (root / "docs" / "recipes.md").read_text(encoding="utf-8")
    rows = [line.replace("**", "") for line in readme.splitlines()]
    return next(line for line in rows if line.startswith(f"| {label} |"))


@pytest.mark.parametrize(
    ("folder", "label"),
    [
        ("L1-8000-shipped", "L1 (shipped as `sh3d-small` before this), from scratch"),
        ("proc-pre-8000", "10,000 procedural shapes only (training: procedural crops)"),
        (
            "proc-ft-8000",
            "the same, then the L1 recipe on the 574 catalogue shapes (the shipped `sh3d-small`)",
        ),
        ("proc-ft-16000", "the same fine-tuning, twice the steps"),
        ("gpu-proc-pre-16000", "10,000 procedural shapes only, twice the steps (H200)"),
        ("proc16-ft-8000", "the 16,000-step pretraining, then the same L1 recipe (this CPU)"),
    ],
)
def test_readme_procedural_pretraining_rows_are_their_files(small_data_runs, folder, label):
    """The table under *Pretraining on procedural shapes*: each row's figures are what the
    script computes from the run's committed files (its name and loss columns aside)."""
    run = Path(__file__).resolve().parent.parent / "results" / "small-data" / folder
    figures = small_data_runs.table_row(small_data_runs.summarise(run)).split(" | ", 3)[3]
    published = _readme_row(label).split(" | ", 2)[2].replace("+", "")
    assert published == figures


SEED_ROWS = [
    ("proc-ft-8000", "seed 0, this CPU (the shipped `sh3d-small`)"),
    *((f"gpu-proc-ft-seed{i}", f"seed {i}, H200") for i in range(6)),
]


@pytest.mark.parametrize(("folder", "label"), SEED_ROWS)
def test_readme_seed_rows_are_their_files(small_data_runs, folder, label):
    """The table under *Seven seeds of the shipped recipe*: each row's figures (training
    onwards) are what the script computes from the run's committed files."""
    run = Path(__file__).resolve().parent.parent / "results" / "small-data" / folder
    figures = small_data_runs.table_row(small_data_runs.summarise(run)).split(" | ", 3)[3]
    assert _readme_row(label).split(" | ", 1)[1] == figures


def test_readme_seed_means_are_those_of_the_seven_runs(small_data_runs):
    """The table's last row: mean ± sample standard deviation of the seven runs."""
    import statistics

    root = Path(__file__).resolve().parent.parent / "results" / "small-data"
    runs = [small_data_runs.summarise(root / folder) for folder, _ in SEED_ROWS]

    def spread(key: str, digits: int) -> str:
        values = [r[key] for r in runs]
        return f"{statistics.mean(values):.{digits}f} ± {statistics.stdev(values):.{digits}f}"

    expected = [
        spread("train", 2),
        spread("val_last_tenth", 2),
        spread("val_best", 2),
        spread("val_f_last_tenth", 3),
        f"{spread('test_best', 2)} / {spread('test_last', 2)}",
        f"{spread('f_best', 4)} / {spread('f_last', 4)}",
    ]
    row = _readme_row("mean ± standard deviation of the seven")
    assert row.strip(" |").split(" | ")[1:] == expected
