"""TrainConfig: presets, TOML files, command-line overrides and validation messages."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from pfnet.commands.train import add_arguments, build_config
from pfnet.errors import ConfigError
from pfnet.training.config import PRESETS, TrainConfig, load_config, preset_config


def _args(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    return parser.parse_args(["--data", "D", "--out", "R", *argv])


def test_paper_preset_is_the_authors_setup() -> None:
    c = preset_config("paper")
    assert (c.model, c.width, c.batch_size, c.missing_ratio) == ("pfnet", 1.0, 36, 0.25)
    assert (c.lr, c.betas, c.eps, c.weight_decay) == (1e-4, (0.9, 0.999), 1e-5, 1e-3)
    assert (c.lr_step, c.lr_gamma, c.adversarial_weight) == (40, 0.2, 0.05)
    assert c.alpha_schedule == ((0, 0.01), (30, 0.05), (80, 0.1))
    assert set(PRESETS) == {"paper", "small"}
    assert preset_config("small").width < 1


def test_n_missing_follows_the_ratio() -> None:
    assert TrainConfig(n_points=2048).n_missing == 512
    assert TrainConfig(n_points=512, missing_ratio=0.5).n_missing == 256


def test_dict_round_trip_is_plain_builtins() -> None:
    c = preset_config("small").replace(n_points=512, seed=3)
    data = c.to_dict()
    assert data["betas"] == [0.9, 0.999] and isinstance(data["alpha_schedule"][0], list)
    assert TrainConfig.from_dict(data) == c


def test_toml_file_on_top_of_a_preset(tmp_path: Path) -> None:
    path = tmp_path / "run.toml"
    path.write_text(
        'preset = "small"\nmodel = "mr-cmlp"\nepochs = 3\nbetas = [0.5, 0.9]\n'
        "alpha_schedule = [[0, 0.1], [2, 0.2]]\n"
    )
    c = load_config(path)
    assert (c.preset, c.model, c.epochs, c.width) == ("small", "mr-cmlp", 3, 0.25)
    assert c.betas == (0.5, 0.9) and c.alpha_schedule == ((0, 0.1), (2, 0.2))
    table = tmp_path / "table.toml"
    table.write_text("[train]\nlr = 0.01\n")
    assert load_config(table, preset="small").lr == 0.01


def test_command_line_overrides_the_file_which_overrides_the_preset(tmp_path: Path) -> None:
    path = tmp_path / "run.toml"
    path.write_text("epochs = 5\nbatch_size = 4\n")
    c = build_config(_args("--preset", "small", "--config", str(path), "--epochs", "7"))
    assert (c.preset, c.epochs, c.batch_size, c.width) == ("small", 7, 4, 0.25)
    c = build_config(_args("--model", "mlp", "--missing-ratio", "0.5", "--lr", "0.002"))
    assert (c.preset, c.model, c.missing_ratio, c.lr) == ("paper", "mlp", 0.5, 0.002)


def test_schedule_and_lr_decay_options_reach_the_config() -> None:
    # --schedule was parsed and then dropped before it was in build_config's names
    c = build_config(_args("--preset", "small", "--schedule", "fixed"))
    assert c.schedule == "fixed"
    assert build_config(_args("--preset", "paper", "--schedule", "run")).schedule == "run"
    c = build_config(_args("--preset", "small", "--steps", "100", "--lr-decay", "cosine"))
    assert (c.steps, c.lr_decay) == (100, "cosine")
    assert build_config(_args("--preset", "small")).lr_decay == "step"
    with pytest.raises(ConfigError, match="cosine needs a run sized to its length"):
        build_config(_args("--preset", "paper", "--lr-decay", "cosine"))


@pytest.mark.parametrize(
    "key, value, match",
    [
        ("model", "pointnet", "model must be one of pfnet, pfnet-vanilla"),
        ("missing_ratio", 1.0, r"missing_ratio must be a number in \(0, 1\)"),
        ("missing_ratio", "0.25", r"missing_ratio must be a number in \(0, 1\); got '0.25'"),
        ("epochs", 0, r"epochs must be an integer in \[1, 1,000,000\]; got 0"),
        ("epochs", 2.5, "epochs must be an integer in"),
        ("batch_size", True, "batch_size must be an integer >= 1; got True"),
        ("lr", -1.0, r"lr must be a number in \(0, 1\]"),
        ("lr", float("nan"), r"lr must be a number in \(0, 1\]"),
        ("betas", (0.9,), r"betas must be two numbers in \[0, 1\)"),
        ("eps", 0.0, "eps must be a positive number"),
        ("weight_decay", -0.1, "weight_decay must be a number >= 0"),
        ("width", 0.0, r"width must be a number in \(0, 4\]"),
        ("lr_step", 0, "lr_step must be an integer >= 1"),
        ("lr_gamma", 1.5, r"lr_gamma must be a number in \(0, 1\]"),
        ("alpha_schedule", ((5, 0.1),), "alpha_schedule must be a list of"),
        ("alpha_schedule", ((0, 0.1), (0, 0.2)), "epochs increasing from 0"),
        ("adversarial_weight", 1.0, r"adversarial_weight must be a number in \[0, 1\)"),
        ("loss_scale", 0, "loss_scale must be a positive number"),
        ("crop", "random", "crop must be one of viewpoint, turned, sphere, multi"),
        ("chamfer", "L1", "chamfer must be one of l2, l1; got 'L1'"),
        ("seed", -1, r"seed must be an integer in \[0, 2\*\*63\)"),
        ("workers", -2, r"workers must be an integer in \[0, 64\]"),
        ("seed", 2**64, r"seed must be an integer in \[0, 2\*\*63\)"),
        ("workers", 100_000, r"workers must be an integer in \[0, 64\]; got 100000"),
        ("n_points", 4, r"n_points must be an integer in \[8, 65536\]"),
        ("n_points", 10**12, r"n_points must be an integer in \[8, 65536\]"),
        ("preset", "huge", "preset must be 'paper' or 'small'"),
    ],
)
def test_bad_values_are_rejected_with_the_key_name(key: str, value: object, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        TrainConfig(**{key: value})


def test_ratio_that_leaves_nothing_missing_is_rejected() -> None:
    with pytest.raises(ConfigError, match="missing_ratio 0.01 removes 0 of 8 points"):
        TrainConfig(n_points=8, missing_ratio=0.01)
    with pytest.raises(ConfigError, match="removes 6 points; at least 1 must be missing and 4"):
        TrainConfig(n_points=8, missing_ratio=0.7)


def test_unknown_keys_and_presets_are_rejected(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="unknown key.*learning_rate; valid keys: model"):
        TrainConfig.from_dict({"learning_rate": 1.0})
    with pytest.raises(ConfigError, match="unknown config key"):
        TrainConfig().replace(colour="red")
    with pytest.raises(ConfigError, match="unknown preset 'huge'; choose one of paper, small"):
        preset_config("huge")


def test_bad_config_files_name_the_file(tmp_path: Path) -> None:
    missing = tmp_path / "nope.toml"
    with pytest.raises(ConfigError, match=f"config file {missing} does not exist"):
        load_config(missing)
    broken = tmp_path / "broken.toml"
    broken.write_text("epochs = = 3\n")
    with pytest.raises(ConfigError, match="broken.toml is not valid TOML"):
        load_config(broken)
    bad = tmp_path / "bad.toml"
    bad.write_text("epochs = -3\n")
    with pytest.raises(
        ConfigError, match=r"bad.toml: epochs must be an integer in \[1, 1,000,000\]; got -3"
    ):
        load_config(bad)
    extra = tmp_path / "extra.toml"
    extra.write_text("epochz = 3\n")
    with pytest.raises(ConfigError, match="extra.toml: unknown key.*epochz"):
        load_config(extra)


def test_resume_takes_the_stored_config_and_refuses_a_preset(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot be combined with --resume"):
        build_config(_args("--resume", "--preset", "small"))
    with pytest.raises(ValueError, match="config.json does not exist"):
        build_config(_args("--resume"))
