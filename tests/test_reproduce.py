"""Tests for ``pfnet reproduce``: the study, its report, and the README's published results."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from pfnet import study as reproduce
from pfnet.cli import main
from pfnet.errors import ConfigError
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

ROOT = Path(__file__).resolve().parent.parent
PUBLISHED = ROOT / "docs" / "results"


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


def _record(model, seed, missing, whole=(1.0, 1.0), curve=(3.0, 2.0, 1.0, 1.0), ratio=0.25):
    """A run record as ``evaluate_run`` makes it; ``missing`` maps category -> (p2g, g2p)."""

    def region(pairs):
        cats = {
            c: {"n": 2, "pred_to_gt": a, "gt_to_pred": b, "cd_l1": a + b, "f_score": 0.5}
            for c, (a, b) in pairs.items()
        }
        mean = {k: sum(c[k] for c in cats.values()) / len(cats) for k in cats[next(iter(cats))]}
        del mean["n"]
        return {"categories": cats, "mean": mean}

    run = StudyRun(model, ratio, seed)
    best = min(range(len(curve)), key=curve.__getitem__)
    return {
        "name": run.name,
        "setting": run.setting,
        "model": model,
        "missing_ratio": ratio,
        "seed": seed,
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

    # Longer schedule: finished runs resume; a third call finds everything trained.
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


@pytest.mark.skipif(not (PUBLISHED / "results.json").is_file(), reason="no published results")
def test_readme_results_are_the_published_run():
    """The README's numbers are generated from docs/results, whose files agree."""
    results = json.loads((PUBLISHED / "results.json").read_text())
    assert readme_section(ROOT / "README.md") == render_report(results, "docs/results/").strip("\n")
    assert (PUBLISHED / "results.md").read_text() == render_report(results)
    assert results["settings"] == reproduce.summarize_settings(results["runs"])
    assert [r["name"] for r in results["runs"]] == [
        r.name for r in study_runs(reproduce.STUDY_MODELS, reproduce.STUDY_RATIOS, results["seeds"])
    ]
    for run in results["runs"]:
        folder = PUBLISHED / "runs" / run["name"]
        for region in ("missing", "whole"):
            report = json.loads((folder / f"eval-{region}.json").read_text())
            assert report["mean"] == run[region]["mean"]
            assert report["categories"] == run[region]["categories"]
        log = [json.loads(line) for line in (folder / "log.jsonl").read_text().splitlines()]
        assert [row["val_cd_l2"] for row in log[1:]] == run["curve"]["val_cd_l2"]
        config = json.loads((folder / "config.json").read_text())
        assert config["model"] == run["model"] and config["missing_ratio"] == run["missing_ratio"]
        assert config["seed"] == run["seed"]
        assert config["epochs"] == results["config"]["epochs"]
        # Every model was trained until validation levelled off.
        assert run["plateau"] == plateau(run["curve"]["val_cd_l2"])
        assert run["plateau"]["levelled"], run["name"]
