"""Tests for ``pfnet reproduce``: the study, its report, and the README's published results."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from pfnet import study as reproduce
from pfnet.cli import main
from pfnet.errors import ConfigError
from pfnet.processes import threads_per_process, usable_cpus
from pfnet.study import (
    README_BEGIN,
    README_END,
    StudyRun,
    plateau,
    readme_section,
    render_report,
    study_runs,
    update_readme,
)
from pfnet.study.aggregate import reported_settings, twice_the_steps
from pfnet.study.record import read_results
from pfnet.study.runs import run_config, study_config
from pfnet.training.config import TrainConfig

ROOT = Path(__file__).resolve().parent.parent
PUBLISHED = ROOT / "results" / "study"
RESULTS_PAGE = ROOT / "docs" / "results.md"  # the study's section, between its markers
AIRPLANES = ROOT / "results" / "airplanes-table5"  # Table 5 on open-shapes' airplanes
AIRPLANES_PAGE = ROOT / "docs" / "airplanes.md"


def test_study_runs_are_the_ablation_then_the_ratios_seed_by_seed():
    runs = study_runs(reproduce.STUDY_MODELS, reproduce.STUDY_RATIOS)
    assert [r.name for r in runs] == [
        "pfnet-25-seed0",
        "pfnet-vanilla-25-seed0",
        "mr-cmlp-25-seed0",
        "cmlp-25-seed0",
        "mlp-25-seed0",
        "pfnet-50-seed0",
        "pfnet-75-seed0",
    ]
    assert study_runs(["mlp"], [0.25, 0.5]) == [StudyRun("mlp", 0.25, 0)]
    runs = study_runs(["pfnet", "mlp"], [0.25, 0.75], seeds=[3, 1])
    assert [r.name for r in runs] == [
        "pfnet-25-seed3",
        "mlp-25-seed3",
        "pfnet-75-seed3",
        "pfnet-25-seed1",
        "mlp-25-seed1",
        "pfnet-75-seed1",
    ]
    assert runs[-1].setting == "pfnet-75" and runs[-1].seed == 1
    # A study sized in steps: every setting at each length, seed by seed, length by length.
    runs = study_runs(["pfnet", "mlp"], [0.25, 0.5], seeds=[0, 1], lengths=[100, 200])
    assert [r.name for r in runs[:6]] == [
        "pfnet-25-100steps-seed0",
        "mlp-25-100steps-seed0",
        "pfnet-50-100steps-seed0",
        "pfnet-25-200steps-seed0",
        "mlp-25-200steps-seed0",
        "pfnet-50-200steps-seed0",
    ]
    assert len(runs) == 12 and runs[-1].steps == 200 and runs[-1].setting == "pfnet-50-200steps"


def _record(
    model, seed, missing, whole=(1.0, 1.0), curve=(3.0, 2.0, 1.0, 1.0), ratio=0.25, steps=None
):
    """A run record as ``evaluate_run`` makes it; ``missing`` maps category -> (p2g, g2p)."""

    def region(pairs):
        cats = {
            c: {"n": 2, "pred_to_gt": a, "gt_to_pred": b, "cd_l1": a + b, "f_score": 0.5}
            for c, (a, b) in pairs.items()
        }
        mean = {k: sum(c[k] for c in cats.values()) / len(cats) for k in cats[next(iter(cats))]}
        del mean["n"]
        return {"categories": cats, "mean": mean}

    run = StudyRun(model, ratio, seed, steps)
    best = min(range(len(curve)), key=curve.__getitem__)
    return {
        "name": run.name,
        "setting": run.setting,
        "model": model,
        "missing_ratio": ratio,
        "seed": seed,
        **({} if steps is None else {"steps": steps}),
        "n_missing": 128,
        "parameters": 1000,
        "train_time_s": 10.0,
        "epoch_time_s": 2.5 + seed,
        "epochs": len(curve),
        "best_epoch": best + 1,
        "best_val_cd_l2": curve[best],
        "plateau": plateau(curve),
        "curve": {"epoch": list(range(1, len(curve) + 1)), "val_cd_l2": list(curve)},
        "missing": region(missing),
        "whole": region({c: whole for c in missing}),
    }


def test_summarize_settings_averages_seeds_and_keeps_the_worst_plateau():
    runs = [
        _record("pfnet", 0, {"chair": (1.0, 2.0), "lamp": (3.0, 4.0)}),
        _record("mlp", 0, {"chair": (5.0, 5.0), "lamp": (5.0, 5.0)}),
        # Still improving in its last quarter: 1.5 -> 1.0 is a 33 % gain.
        _record("pfnet", 1, {"chair": (2.0, 2.0), "lamp": (5.0, 6.0)}, curve=(3, 2, 1.5, 1.0)),
        _record("mlp", 1, {"chair": (4.0, 6.0), "lamp": (6.0, 4.0)}),
    ]
    pfnet, mlp = reproduce.summarize_settings(runs)
    assert (pfnet["name"], mlp["name"]) == ("pfnet-25", "mlp-25")
    assert pfnet["seeds"] == [0, 1] and pfnet["best_epochs"] == [3, 4]
    chair = pfnet["missing"]["categories"]["chair"]
    assert chair == {"n": 2, "pred_to_gt": 1.5, "gt_to_pred": 2.0, "cd_l1": 3.5, "f_score": 0.5}
    # Seed means over categories: p2g 2.0 and 3.5, g2p 3.0 and 4.0.
    assert pfnet["missing"]["mean"]["pred_to_gt"] == pytest.approx(2.75)
    assert pfnet["missing"]["std"]["pred_to_gt"] == pytest.approx(1.5 / 2**0.5)
    assert pfnet["missing"]["std"]["gt_to_pred"] == pytest.approx(1.0 / 2**0.5)
    assert pfnet["train_time_s"] == 20.0 and pfnet["epoch_time_s"] == 3.0
    assert pfnet["best_val_cd_l2"] == pytest.approx(1.0)
    assert pfnet["plateau"]["seed"] == 1 and pfnet["plateau"]["gain"] == pytest.approx(1 / 3)
    assert not pfnet["plateau"]["levelled"] and mlp["plateau"]["levelled"]
    # One seed: no spread.
    (single,) = reproduce.summarize_settings(runs[:1])
    assert single["missing"]["std"]["pred_to_gt"] is None
    assert single["missing"]["mean"] == runs[0]["missing"]["mean"]


def test_report_tables_and_claims_use_the_seed_means():
    runs = [
        _record("pfnet-vanilla", 0, {"chair": (1.0, 1.0)}),
        _record("mr-cmlp", 0, {"chair": (2.0, 2.0)}),
        _record("pfnet-vanilla", 1, {"chair": (3.0, 3.0)}),
        _record("mr-cmlp", 1, {"chair": (2.5, 2.5)}),
    ]
    settings = reproduce.summarize_settings(runs)
    table = reproduce.region_table(settings, "missing")
    assert table[0] == "| category | n | PF-Net (vanilla) | MR-CMLP |"
    assert table[2] == "| chair | 2 | 2.000 / 2.000 | 2.250 / 2.250 |"
    assert table[3] == "| **mean** | | **2.000 / 2.000** | 2.250 / 2.250 |"
    assert table[4] == "| std over seeds | | ± 1.414 / ± 1.414 | ± 0.354 / ± 0.354 |"
    header, _, row = reproduce.claims_table(settings, runs)
    assert header.startswith("| the paper's claim | models | Pred→GT | GT→Pred | CD-L2 |")
    assert row == (
        "| the point pyramid decoder helps | PF-Net (vanilla) vs MR-CMLP | 2.000 vs 2.250 ✓ "
        "| 2.000 vs 2.250 ✓ | 4.000 vs 4.500 ✓ | 1 of 2 | 1 of 1 |"
    )
    # A claim that fails on one metric and holds on the other.
    runs = [
        _record("pfnet", 0, {"chair": (1.0, 3.0), "lamp": (1.0, 1.0)}),
        _record("pfnet-vanilla", 0, {"chair": (2.0, 1.0), "lamp": (2.0, 2.0)}),
    ]
    row = reproduce.claims_table(reproduce.summarize_settings(runs), runs)[2]
    assert row == (
        "| the adversarial loss helps | PF-Net vs PF-Net (vanilla) | 1.000 vs 2.000 ✓ "
        "| 2.000 vs 1.500 ✗ | 3.000 vs 3.500 ✓ | 1 of 1 | 1 of 2 |"
    )


def test_twice_the_steps_shows_the_shortest_length_every_setting_converged_at():
    chair = {"chair": (1.0, 1.0)}

    def study(mlp_curves):
        return [
            # pfnet: 100 -> 200 steps gains 20 % (still improving), 200 -> 400 gains 2 %.
            _record("pfnet", 0, chair, curve=(9.0, 5.0), steps=100),
            _record("pfnet", 0, {"chair": (0.5, 0.5)}, curve=(9.0, 4.0), steps=200),
            _record("pfnet", 0, chair, curve=(9.0, 3.92), steps=400),
            *(
                _record("mlp", 0, {"chair": (c, c)}, curve=(9.0, c), steps=n)
                for c, n in zip(mlp_curves, (100, 200, 400), strict=True)
            ),
        ]

    # mlp converged at 200 too: both tables show 200 steps.
    settings = reproduce.summarize_settings(study((6.0, 5.0, 4.96)))
    assert [s["steps"] for s in settings] == [100, 200, 400, 100, 200, 400]
    test = twice_the_steps(settings, 0.03)
    assert (test["lengths"], test["shown"], test["all_converged"]) == ([100, 200, 400], 200, True)
    pfnet, mlp = test["entries"]
    assert pfnet["gains"] == pytest.approx([0.2, 0.02]) and pfnet["converged"] == [False, True]
    assert [s["name"] for s in reported_settings(settings, 0.03)] == [
        "pfnet-25-200steps",
        "mlp-25-200steps",
    ]
    # mlp gains more than 3 % at every doubling: the tables show the longest length.
    runs = study((8.0, 7.0, 6.0))
    settings = reproduce.summarize_settings(runs)
    test = twice_the_steps(settings, 0.03)
    assert (test["shown"], test["all_converged"]) == (400, False)
    assert test["entries"][1]["converged"] == [False, False]
    results = {
        "settings": settings,
        "runs": runs,
        "seeds": [0],
        "dataset": {"source": "x", "points": 512, "splits": {"train": 1}, "credits": []},
        "train_dataset": {"source": "y", "points": 512, "splits": {"train": 9}},
        "machine": {"device": "cpu", "name": "x", "torch_threads": 2, "torch": "2"},
        "config": {
            "width": 0.25,
            "batch_size": 16,
            "lr": 0.001,
            "lr_gamma": 0.2,
            "lr_step": 40,
            "epochs": 200,
            "lr_milestones": [0.5, 0.75],
        },
        "preset": "small",
        "study_time_s": 60.0,
    }
    report = render_report(results)
    assert "every setting trained for 100 and 200 and 400 optimiser steps" in report
    assert "trained on the train split of **y** (9 train)" in report
    assert "so the tables above show the longest, 400 steps" in report
    assert "| chair | 2 | 1.000 / 1.000 | 6.000 / 6.000 |" in report  # both at 400 steps
    assert "| PF-Net, 25% | 1,000 | 100 | 2 / 2 | 5.000 | 2.000 | 0.2 min | +20.0%: still" in report
    assert "| PF-Net, 25% | 1,000 | 200 | 2 / 2 | 4.000 | 1.000 | 0.2 min | +2.0%: conv" in report
    assert (
        "| MLP, 25% | 1,000 | **400** | 2 / 2 | 6.000 | 12.000 | 0.2 min | not tested |" in report
    )


def test_plateau_measures_the_last_quarter():
    falling = [100.0 / (k + 1) for k in range(40)]
    result = plateau(falling)
    assert result["window"] == 10 and not result["levelled"]
    assert result["gain"] == pytest.approx((100 / 30 - 100 / 40) / (100 / 30))
    flat = [10.0] * 19 + [9.95] + [9.96] * 20
    assert plateau(flat) == {"window": 10, "gain": pytest.approx(-0.01 / 9.95), "levelled": True}
    worse = [5.0] * 30 + [6.0] * 10
    assert plateau(worse)["gain"] == pytest.approx(-0.2) and plateau(worse)["levelled"]
    assert plateau([3.0, 2.0, 1.0]) == {"window": 0, "gain": None, "levelled": False}


def test_update_readme_replaces_only_the_section(tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text(f"# title\n\nbefore\n{README_BEGIN}\nold\n{README_END}\nafter\n")
    update_readme(readme, "new table\n")
    assert (
        readme.read_text() == f"# title\n\nbefore\n{README_BEGIN}\nnew table\n{README_END}\nafter\n"
    )
    assert readme_section(readme) == "new table"
    readme.write_text("# no markers\n")
    with pytest.raises(ConfigError, match="no results section; add the lines"):
        update_readme(readme, "x")
    with pytest.raises(ConfigError, match="cannot read it"):
        update_readme(tmp_path / "absent.md", "x")


def test_reproduce_argument_errors(tmp_path, capsys):
    out = str(tmp_path / "r")
    assert main(["reproduce", "--out", out, "--models", "pfnet", "pointnet"]) == 1
    assert "--models: unknown model(s) pointnet; choose from pfnet" in capsys.readouterr().err
    assert main(["reproduce", "--out", out, "--ratios", "0.25", "1.5"]) == 1
    assert "--ratios must be in (0, 1); got 1.5" in capsys.readouterr().err
    assert main(["reproduce", "--out", out, "--readme", str(tmp_path / "none.md")]) == 1
    assert "--readme" in capsys.readouterr().err
    assert main(["reproduce", "--out", out, "--report-only"]) == 1
    assert f"--report-only: cannot read {out}/results.json" in capsys.readouterr().err
    pytest.importorskip("torch")  # the checks below come after the device is resolved
    assert main(["reproduce", "--out", out, "--data", str(tmp_path), "--device", "cpu"]) == 1
    assert "is not a prepared data set (no manifest.json)" in capsys.readouterr().err


@pytest.mark.slow
def test_reproduce_end_to_end_resumes_publishes_and_fills_the_readme(
    tmp_path, tiny_dataset, capsys
):
    pytest.importorskip("torch")
    out, pub = tmp_path / "study", tmp_path / "docs" / "results"
    readme = tmp_path / "README.md"
    readme.write_text(f"# x\n{README_BEGIN}\n{README_END}\n")
    argv = ["reproduce", "--out", str(out), "--data", str(tiny_dataset), "--device", "cpu"]
    argv += ["--models", "pfnet", "mlp", "--ratios", "0.25", "0.5", "--width", "0.125"]
    argv += ["--batch-size", "8", "--gallery-count", "2", "--seeds", "0", "1"]
    assert main([*argv, "--epochs", "2"]) == 0
    text = capsys.readouterr().out
    assert "pfnet-25-seed0: training 2 epochs on cpu" in text

    results = json.loads((out / "results.json").read_text())
    assert [r["name"] for r in results["runs"]] == [
        f"{setting}-seed{seed}" for seed in (0, 1) for setting in ("pfnet-25", "mlp-25", "pfnet-50")
    ]
    assert [s["name"] for s in results["settings"]] == ["pfnet-25", "mlp-25", "pfnet-50"]
    assert results["settings"] == reproduce.summarize_settings(results["runs"])
    assert results["seeds"] == [0, 1] and "seed" not in results["config"]
    for seed in (0, 1):
        config = json.loads((out / "runs" / f"mlp-25-seed{seed}" / "config.json").read_text())
        assert config["seed"] == seed
    # Different seeds train different networks.
    assert results["runs"][0]["curve"] != results["runs"][3]["curve"]
    assert results["preset"] == "small" and results["config"]["width"] == 0.125
    assert results["dataset"]["splits"] == {"train": 24, "val": 8, "test": 12}
    for run in results["runs"]:
        assert run["epochs"] == 2 and len(run["curve"]["val_cd_l2"]) == 2
        assert run["n_missing"] == round(512 * run["missing_ratio"])
        for region in ("missing", "whole"):
            report = json.loads((out / "runs" / run["name"] / f"eval-{region}.json").read_text())
            assert report["region"] == region and report["missing"] == []
            assert run[region]["mean"] == report["mean"]
            assert sum(c["n"] for c in run[region]["categories"].values()) == 12
    mean = results["settings"][0]["missing"]["mean"]["pred_to_gt"]
    seed_means = [results["runs"][k]["missing"]["mean"]["pred_to_gt"] for k in (0, 3)]
    assert mean == pytest.approx(sum(seed_means) / 2)
    for name in ("curves.png", "gallery.png"):
        assert (out / name).read_bytes()[:4] == b"\x89PNG"
    report = (out / "results.md").read_text()
    assert report == render_report(results)
    assert "| **mean** |" in report and "PF-Net at 25 / 50 / 75 % missing" in report

    # Longer schedule: finished runs resume (one written before a configuration key existed,
    # which takes its default); a third call finds everything trained.
    stored = out / "runs" / "pfnet-25-seed1" / "config.json"
    older = {k: v for k, v in json.loads(stored.read_text()).items() if k != "ema"}
    stored.write_text(json.dumps(older))
    assert main([*argv, "--epochs", "3"]) == 0
    assert "pfnet-25-seed1: resuming at epoch 3 of 3" in capsys.readouterr().out
    assert main([*argv, "--epochs", "3", "--publish", str(pub), "--readme", str(readme)]) == 0
    text = capsys.readouterr().out
    assert "mlp-25-seed0: already trained (3 epochs)" in text
    assert f"updated the results section of {readme}" in text
    results = json.loads((pub / "results.json").read_text())
    assert [r["epochs"] for r in results["runs"]] == [3] * 6
    assert readme_section(readme) == render_report(results, "docs/results/").strip("\n")
    published = sorted(str(p.relative_to(pub)) for p in pub.rglob("*") if p.is_file())
    assert not [p for p in published if p.endswith(".pt") or "predictions" in p]
    assert "runs/mlp-25-seed1/log.jsonl" in published and "gallery.png" in published

    # Another configuration in the same folder is refused, not mixed in.
    assert main([*argv, "--epochs", "3", "--width", "0.25"]) == 1
    assert "holds a run with another configuration" in capsys.readouterr().err

    # The report alone is rebuilt from results.json.
    (out / "results.md").unlink()
    assert main(["reproduce", "--out", str(out), "--data", str(tiny_dataset), "--report-only"]) == 0
    assert (out / "results.md").read_text() == render_report(
        json.loads((out / "results.json").read_text())
    )


@pytest.mark.slow
def test_reproduce_in_steps_side_by_side_on_other_training_data(tmp_path, tiny_dataset, capfd):
    """--steps N 2N trains every setting at both lengths, --jobs 2 two at a time in their own
    processes, --train-data on another data set's train split; the record reads back."""
    pytest.importorskip("torch")
    import shutil

    train_data = tmp_path / "train-data"
    shutil.copytree(tiny_dataset, train_data)
    out = tmp_path / "study"
    argv = ["reproduce", "--out", str(out), "--data", str(tiny_dataset), "--device", "cpu"]
    argv += ["--models", "pfnet-vanilla", "mlp", "--ratios", "0.25", "--width", "0.125"]
    argv += ["--batch-size", "8", "--gallery-count", "1", "--seeds", "0", "--steps", "6", "3"]
    argv += ["--chamfer", "l1", "--train-data", str(train_data), "--jobs", "2"]
    assert main(argv) == 0
    text = capfd.readouterr().out
    assert "mlp-25-6steps-seed0: training 6 steps on cpu" in text
    threads = threads_per_process(2)
    assert f"2 runs at a time, {threads} torch thread(s) each" in text
    results = read_results(out / "results.json")
    assert results["machine"]["torch_threads"] == threads
    names = ["pfnet-vanilla-25-3steps", "mlp-25-3steps", "pfnet-vanilla-25-6steps", "mlp-25-6steps"]
    assert [r["name"] for r in results["runs"]] == [f"{n}-seed0" for n in names]
    assert [s["steps"] for s in results["settings"]] == [3, 3, 6, 6]
    assert results["train_dataset"]["splits"]["train"] == 24
    for run in results["runs"]:
        folder = out / "runs" / run["name"]
        config = json.loads((folder / "config.json").read_text())
        assert (config["steps"], config["chamfer"]) == (run["steps"], "l1")
        log = [json.loads(line) for line in (folder / "log.jsonl").read_text().splitlines()]
        assert log[-1]["step"] == run["steps"] and run["epochs"] == run["steps"] // 3
    report = (out / "results.md").read_text()
    assert report == render_report(results) and "the twice-the-steps test" in report
    assert "loss on the Chamfer distances, not their squares (`--chamfer l1`)" in report
    assert (out / "gallery.png").read_bytes()[:4] == b"\x89PNG"
    # Again: everything is trained; the report alone is rebuilt from the record.
    assert main(argv) == 0
    assert "mlp-25-3steps-seed0: already trained (3 steps)" in capfd.readouterr().out
    assert main(["reproduce", "--out", str(out), "--data", str(tiny_dataset), "--report-only"]) == 0
    # Audit 11: runs trained on another data set are not taken as trained on this one, and
    # training data of another point count is refused before any training.
    from pfnet.data import prepare_dataset

    for name, points, seed in (("other", 512, 1), ("sparse", 256, 0)):
        prepare_dataset(
            None,
            tmp_path / name,
            format="procedural",
            points=points,
            seed=seed,
            count=3,
            categories=["chair"],
            workers=1,
            progress=False,
        )
    rest = argv[: argv.index("--train-data")] + ["--jobs", "1"]
    assert main([*rest, "--train-data", str(tmp_path / "other")]) == 1
    assert "holds a run trained on another data set" in capfd.readouterr().err
    assert main([*rest, "--train-data", str(tmp_path / "sparse")]) == 1
    assert "holds clouds of 256 points, the study's data set" in capfd.readouterr().err


def test_runs_side_by_side_share_the_cores_out(monkeypatch: pytest.MonkeyPatch) -> None:
    assert [threads_per_process(n, 2) for n in (1, 2, 3, 14)] == [2, 1, 1, 1]
    assert [threads_per_process(n, 16) for n in (0, 1, 3, 14)] == [16, 16, 5, 1]
    assert 1 <= threads_per_process(4) <= usable_cpus()
    # The process of a run trains on the threads it is given.
    torch = pytest.importorskip("torch")
    from pfnet.study import orchestrate

    seen = []

    def train_run(*args, **kwargs):
        seen.append(torch.get_num_threads())

    monkeypatch.setattr(orchestrate, "train_run", train_run)
    before = torch.get_num_threads()
    given = 1 if before != 1 else 2  # not what it has already
    try:
        orchestrate._train_in_process(None, None, Path("."), Path("."), "cpu", None, "", given)
    finally:
        torch.set_num_threads(before)
    assert seen == [given]


def test_reproduce_length_and_job_options_are_checked(tmp_path, capsys):
    out = ["reproduce", "--out", str(tmp_path / "r")]
    for extra, problem in (
        (["--steps", "0"], "--steps: run lengths must be different integers >= 1"),
        (["--steps", "5", "5"], "--steps: run lengths must be different integers >= 1"),
        (["--steps", "1", "2", "3", "4", "5"], "--steps: at most 4 run lengths"),
        (["--steps", "5", "--epochs", "3"], "--epochs and --steps size the runs two ways"),
        (["--jobs", "0"], "--jobs must be between 1 and 64; got 0"),
        (["--steps", "100000001"], "--steps: at most 100,000,000 steps a run"),
    ):
        assert main([*out, *extra]) == 1
        assert problem in capsys.readouterr().err
    pytest.importorskip("torch")  # the data checks come after the device is resolved
    argv = [*out, "--data", str(tmp_path), "--train-data", str(tmp_path / "x"), "--device", "cpu"]
    (tmp_path / "manifest.json").write_text("{}")
    assert main(argv) == 1
    assert f"--train-data {tmp_path / 'x'} is not a prepared data set" in capsys.readouterr().err


@pytest.mark.skipif(not (PUBLISHED / "results.json").is_file(), reason="no published results")
def test_readme_results_are_the_published_run():
    """The results page's numbers are generated from results/study, whose files agree; the
    10,000-step runs of results/study/longer-runs are the page's twice-the-steps table."""
    results = json.loads((PUBLISHED / "results.json").read_text())
    assert readme_section(RESULTS_PAGE) == render_report(results, "results/").strip("\n")
    for folder in (PUBLISHED, PUBLISHED / "longer-runs"):
        record = read_results(folder / "results.json")  # checked whole, as --report-only does
        assert (folder / "results.md").read_text() == render_report(record)
        for run in record["runs"]:
            _check_published_run(folder / "runs" / run["name"], run)
    # The README's table of 5,000 against 10,000 steps: the two records' validation gains.
    longer = read_results(PUBLISHED / "longer-runs" / "results.json")
    by_name = {s["name"]: s for s in results["settings"]}
    readme = RESULTS_PAGE.read_text()
    for setting in longer["settings"]:
        before = by_name[setting["name"].replace("10000steps", "5000steps")]
        a, b = before["best_val_cd_l2"], setting["best_val_cd_l2"]
        assert f"| {a:.3f} | {b:.3f} | {(a - b) / a:+.1%}: " in readme, setting["name"]


@pytest.mark.skipif(not (PUBLISHED / "cpu-runs").is_dir(), reason="no runs of the CPU")
def test_readme_twice_the_steps_rows_of_the_cpu_runs_are_their_files():
    """The runs benchmarks/study_run.py trained on a CPU (results/study/cpu-runs): each has
    the study's configuration, its files agree with its record, and the results page's row is its
    validation gain over the run of half its length (published in either record or here)."""
    records = {
        run["name"]: run
        for folder in (PUBLISHED, PUBLISHED / "longer-runs")
        for run in read_results(folder / "results.json")["runs"]
    }
    cpu = sorted((PUBLISHED / "cpu-runs").iterdir())
    assert cpu
    for folder in cpu:
        records[folder.name] = json.loads((folder / "record.json").read_text())
    readme = RESULTS_PAGE.read_text()
    base = study_config("small")
    for folder in cpu:
        run = records[folder.name]
        assert run["name"] == folder.name
        _check_published_run(folder, run)
        # Through TrainConfig: a key added since the run was published takes its default,
        # which is what the run trained with.
        config = TrainConfig.from_dict(json.loads((folder / "config.json").read_text())).to_dict()
        study = StudyRun(run["model"], run["missing_ratio"], run["seed"], run["steps"])
        wanted = run_config(study, base).to_dict()
        assert {k: v for k, v in config.items() if k != "n_points"} == {
            k: v for k, v in wanted.items() if k != "n_points"
        }, folder.name
        half = records[folder.name.replace(f"-{run['steps']}steps", f"-{run['steps'] // 2}steps")]
        a, b = half["best_val_cd_l2"], run["best_val_cd_l2"]
        assert f"| {a:.3f} | {b:.3f} | {(a - b) / a:+.1%}: " in readme, folder.name


def _check_published_run(folder: Path, run: dict) -> None:
    for region in ("missing", "whole"):
        report = json.loads((folder / f"eval-{region}.json").read_text())
        assert report["mean"] == run[region]["mean"]
        assert report["categories"] == run[region]["categories"]
    log = [json.loads(line) for line in (folder / "log.jsonl").read_text().splitlines()]
    assert [row["val_cd_l2"] for row in log[1:]] == run["curve"]["val_cd_l2"]
    assert log[-1]["step"] == run["steps"]  # the run reached its length
    config = json.loads((folder / "config.json").read_text())
    assert config["model"] == run["model"] and config["missing_ratio"] == run["missing_ratio"]
    assert config["seed"] == run["seed"] and config["steps"] == run["steps"]
    assert run["plateau"] == plateau(run["curve"]["val_cd_l2"])


def test_dataset_summary_names_the_catalogues_of_several_sources():
    """A data set of FlightGear's and crrcsim's airplanes is named by its catalogues (not
    ``several``), and by the sources' short names when the catalogues' would be too long."""
    from pfnet.study.orchestrate import _dataset_summary

    licences = [
        {"source": "flightgear", "catalogue": "FlightGear models", "license": "GPL-2+"},
        {"source": "crrcsim", "catalogue": "crrcsim model aircraft", "license": "GPL-2"},
    ]
    manifest = {
        "source": {"format": "several", "sources": []},
        "points": 2048,
        "splits": {"train": {"total": 3}, "val": {"total": 1}, "test": {"total": 1}},
        "licenses": licences,
    }
    summary = _dataset_summary(manifest)
    assert summary["source"] == "FlightGear models and crrcsim model aircraft"
    assert summary["credits"] == ["FlightGear models (GPL-2+)", "crrcsim model aircraft (GPL-2)"]
    licences[0]["catalogue"] = "x" * 200
    assert _dataset_summary(manifest)["source"] == "flightgear and crrcsim"


@pytest.mark.skipif(
    not (AIRPLANES / "ablation" / "results.json").is_file(), reason="no published ablation"
)
def test_airplanes_ablation_section_is_its_published_record():
    """The five-model ablation on airplanes: its record's files agree with its results.json,
    and the page's tables are the record's tables, word for word."""
    folder = AIRPLANES / "ablation"
    record = read_results(folder / "results.json")
    assert (folder / "results.md").read_text() == render_report(record)
    assert {run["model"] for run in record["runs"]} == {
        "pfnet",
        "pfnet-vanilla",
        "mr-cmlp",
        "cmlp",
        "mlp",
    }
    assert {run["missing_ratio"] for run in record["runs"]} == {0.25}
    for run in record["runs"]:
        _check_published_run(folder / "runs" / run["name"], run)
    section = AIRPLANES_PAGE.read_text().split("## The five models at 25 % missing")[1]
    blocks = [
        block
        for block in (folder / "results.md").read_text().split("\n\n")
        if block.startswith(("| category", "| the paper's claim", "| setting", "Ranking by"))
    ]
    assert len(blocks) == 5
    for block in blocks:
        assert block in section, block[:60]


def _check_longer_run(
    shorter: Path, longer: Path, model: str, steps: int, more: int, added: dict | None = None
) -> tuple[float, dict]:
    """Check that ``longer``'s run of ``model`` is ``shorter``'s with only the length changed
    (and the ``added`` keys at those values) and ran to the end; give its best validation
    CD-L2 and its test figures of the missing region."""
    run = longer / "runs" / f"{model}-25-{more}steps-seed0"
    half = shorter / "runs" / f"{model}-25-{steps}steps-seed0"
    config, stored = (json.loads((d / "config.json").read_text()) for d in (run, half))
    assert config.pop("steps") == more and stored.pop("steps") == steps
    for key, value in (added or {}).items():
        assert config.pop(key) == value, (model, key)
    assert config == stored, model
    log = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert log[-1]["step"] == more
    best = min(row["val_cd_l2"] for row in log[1:])
    return best, json.loads((run / "eval-missing.json").read_text())["mean"]


def test_airplanes_ablation_at_4000_steps_is_its_record():
    """The twice-the-steps runs of the ablation's four models (4,000 steps) are the study's
    2,000-step runs with only the length changed; the page quotes their record's figures."""
    folder = AIRPLANES / "ablation-4000"
    record = json.loads((folder / "runs.json").read_text())
    assert set(record) == {"pfnet-vanilla", "mr-cmlp", "cmlp", "mlp"}
    section = AIRPLANES_PAGE.read_text().split("### Twice the steps for the four")[1]
    for model, entry in record.items():
        # keys added since the 2,000-step runs, at the values those runs trained with
        added = {"batchnorm_freeze": 0.0, "lr_decay": "step"}
        best, missing = _check_longer_run(AIRPLANES / "ablation", folder, model, 2000, 4000, added)
        assert best == entry["steps_4000"]["best_val_cd_l2"]
        assert missing == entry["steps_4000"]["test_missing"]
        test = missing["pred_to_gt"] + missing["gt_to_pred"]
        for figure in (best, test):
            assert f"{figure:.3f}" in section, (model, figure)


def _check_twice_the_steps(shorter: str, longer: str, steps: int, heading: str) -> set[str]:
    """Check a record of runs at twice ``steps`` (``longer``) against the record of the runs
    at ``steps`` (``shorter``): each run is its shorter run with only the length changed, the
    record's gains are its own figures, and the page's section ``heading`` quotes both
    lengths. Give the record's models."""
    more = 2 * steps
    folder = AIRPLANES / longer
    record = json.loads((folder / "runs.json").read_text())
    before_record = json.loads((AIRPLANES / shorter / "runs.json").read_text())
    section = AIRPLANES_PAGE.read_text().split(heading)[1].split("\n## ")[0]
    for model, entry in record.items():
        best, missing = _check_longer_run(AIRPLANES / shorter, folder, model, steps, more)
        assert best == entry[f"steps_{more}"]["best_val_cd_l2"]
        assert missing == entry[f"steps_{more}"]["test_missing"]
        test = missing["pred_to_gt"] + missing["gt_to_pred"]
        assert test == pytest.approx(entry[f"steps_{more}"]["test_cd_l2"])
        before = before_record[model][f"steps_{steps}"]
        assert entry[f"steps_{steps}"]["best_val_cd_l2"] == before["best_val_cd_l2"]
        assert entry[f"steps_{steps}"]["test_cd_l2"] == pytest.approx(before["test_cd_l2"])
        gain = 1 - best / before["best_val_cd_l2"]
        assert entry[f"val_gain_of_{more}_over_{steps}"] == pytest.approx(gain)
        for figure in (before["best_val_cd_l2"], best, before["test_cd_l2"], test):
            assert f"{figure:.3f}" in section, (model, figure)
        change = f"\u2212{100 * gain:.1f} %" if gain > 0 else f"+{-100 * gain:.1f} %"
        assert change in section, (model, change)
    return set(record)


def test_airplanes_ablation_at_8000_steps_is_its_record():
    """The four models again at 8,000 steps: the 4,000-step runs with only the length changed;
    the record's gains are its own figures, and the page quotes both lengths."""
    models = _check_twice_the_steps("ablation-4000", "ablation-8000", 4000, "### 8,000 steps")
    assert models == {"pfnet-vanilla", "mr-cmlp", "cmlp", "mlp"}


def test_airplanes_ablation_at_16000_steps_is_its_record():
    """CMLP and MLP, still improving at 8,000 steps, at 16,000, checked the same way."""
    models = _check_twice_the_steps("ablation-8000", "ablation-16000", 8000, "### 16,000 steps")
    assert models == {"cmlp", "mlp"}


@pytest.mark.skipif(not (AIRPLANES / "results.json").is_file(), reason="no published airplanes")
def test_airplanes_page_is_its_published_record():
    """docs/airplanes.md's section is generated from results/airplanes-table5, whose files
    agree with it; the anchors' figures quoted in the page are the anchors' JSON files."""
    results = json.loads((AIRPLANES / "results.json").read_text())
    assert readme_section(AIRPLANES_PAGE) == render_report(results, "airplanes/").strip("\n")
    record = read_results(AIRPLANES / "results.json")
    assert (AIRPLANES / "results.md").read_text() == render_report(record)
    assert {run["model"] for run in record["runs"]} == {"pfnet"}
    assert {run["missing_ratio"] for run in record["runs"]} == {0.25, 0.5, 0.75}
    for run in record["runs"]:
        _check_published_run(AIRPLANES / "runs" / run["name"], run)
    page = AIRPLANES_PAGE.read_text()
    for ratio in ("0.25", "0.5", "0.75"):
        oracle = json.loads((AIRPLANES / "anchors" / f"surface-oracle-{ratio}.json").read_text())
        assert f"{oracle['oracle']['mean']['cd_l2']:.3f}" in page, ratio
        assert f"{oracle['floor']['mean']['cd_l2']:.2f}" in page, ratio
