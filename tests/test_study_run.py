"""benchmarks/study_run.py: single runs of the study by name, as ``pfnet reproduce`` trains them."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("torch")  # the study's runs are training runs (the light install has none)

from scripts import load_script  # noqa: E402

from pfnet.errors import ConfigError  # noqa: E402
from pfnet.study.runs import StudyRun, run_config, study_config  # noqa: E402


@pytest.fixture(scope="module")
def study_run():
    return load_script("study_run")


def test_run_names_are_parsed_back_to_the_study_runs(study_run):
    assert study_run.parse_run("pfnet-50-10000steps-seed0") == StudyRun("pfnet", 0.5, 0, 10000)
    assert study_run.parse_run("mr-cmlp-25-20000steps-seed3") == StudyRun("mr-cmlp", 0.25, 3, 20000)
    assert study_run.parse_run("pfnet-vanilla-75-8steps-seed1").model == "pfnet-vanilla"


@pytest.mark.parametrize(
    "name", ["pointnet-25-100steps-seed0", "pfnet-25-seed0", "pfnet-0-100steps-seed0", "mlp"]
)
def test_names_that_are_not_study_runs_are_refused_before_training(study_run, name, tmp_path):
    with pytest.raises(SystemExit) as err:
        study_run.main(["mlp-25-4steps-seed0", name, "--out", str(tmp_path), "--data", "x"])
    assert f"{name!r} is not a study run name" in str(err.value)
    assert not any(tmp_path.iterdir())  # the good name before it was not trained either


def test_a_run_trains_with_the_study_config_scores_and_is_not_trained_twice(
    study_run, tiny_dataset, tmp_path, capsys
):
    argv = ["mlp-25-4steps-seed0", "--out", str(tmp_path), "--data", str(tiny_dataset)]
    assert study_run.main([*argv, "--threads", "1"]) == 0
    run_dir = tmp_path / "mlp-25-4steps-seed0"
    record = json.loads((run_dir / "record.json").read_text())
    assert record["name"] == "mlp-25-4steps-seed0" and record["steps"] == 4
    assert set(record["missing"]["categories"]) == {"chair", "lamp", "sofa", "table"}
    stored = json.loads((run_dir / "config.json").read_text())
    wanted = run_config(StudyRun("mlp", 0.25, 0, 4), study_config("small")).to_dict()
    assert {k: v for k, v in stored.items() if k != "n_points"} == {
        k: v for k, v in wanted.items() if k != "n_points"
    }
    assert "best val CD-L2" in capsys.readouterr().out
    assert study_run.main(argv) == 0
    assert "mlp-25-4steps-seed0: already trained (4 steps)" in capsys.readouterr().out


def test_a_run_trains_with_a_config_file_over_the_preset(study_run, tiny_dataset, tmp_path):
    config = tmp_path / "published.toml"
    config.write_text('lr = 0.0005\nbatchnorm_freeze = 0.0\nlr_decay = "step"\nseed = 5\n')
    out = tmp_path / "runs"
    argv = ["mlp-25-4steps-seed0", "--out", str(out), "--data", str(tiny_dataset)]
    assert study_run.main([*argv, "--threads", "1", "--config", str(config)]) == 0
    stored = json.loads((out / "mlp-25-4steps-seed0" / "config.json").read_text())
    # the file's keys over the small preset; the name's model, ratio, seed and length
    assert stored["lr"] == 0.0005 and stored["batchnorm_freeze"] == 0.0
    assert stored["preset"] == "small" and stored["grad_clip"] == 2.0
    assert (stored["model"], stored["missing_ratio"], stored["seed"]) == ("mlp", 0.25, 0)
    assert stored["steps"] == 4
    # the study's own configuration is another one: the run is not mixed with it
    with pytest.raises(ConfigError, match="holds a run with another configuration"):
        study_run.main(argv)
