"""benchmarks/ship_model.py: a checkpoint turned into a model file with a measured card."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

pytest.importorskip("torch")

from scripts import load_script  # noqa: E402

from pfnet.data import prepare_dataset, read_manifest  # noqa: E402
from pfnet.evaluation.scoring import evaluate_predictions  # noqa: E402
from pfnet.inference.checkpoint import save_checkpoint  # noqa: E402
from pfnet.inference.predict import predict_split  # noqa: E402
from pfnet.inference.shipped import read_metadata  # noqa: E402
from pfnet.models import build_model  # noqa: E402
from pfnet.training.config import preset_config  # noqa: E402


@pytest.fixture(scope="module")
def ship_model():
    return load_script("ship_model")


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An untrained 512-point generator, as ``best.pt`` of a run."""
    config = preset_config("small").replace(n_points=512, width=0.125, model="pfnet-vanilla")
    path = tmp_path_factory.mktemp("run") / "best.pt"
    save_checkpoint(path, {"config": config.to_dict(), "model": build_model(config).state_dict()})
    return path


def _procedural(out: Path, categories: list[str], count: int, test_fraction: float) -> Path:
    prepare_dataset(
        None,
        out,
        format="procedural",
        points=512,
        seed=0,
        count=count,
        categories=categories,
        test_fraction=test_fraction,
        val_fraction=0.0,
        workers=1,
        progress=False,
    )
    return out


def _args(checkpoint: Path, train: Path, test: Path, out_dir: Path) -> list[str]:
    return [
        str(checkpoint),
        "--name",
        "tiny",
        "--train-data",
        str(train),
        "--test-data",
        str(test),
        "--summary",
        "a tiny model",
        "--recipe",
        "pfnet train ...",
        "--out-dir",
        str(out_dir),
    ]


def test_the_card_holds_the_test_score_of_the_written_file_and_both_data_sets(
    ship_model, checkpoint, tiny_dataset, tmp_path
):
    pretrain = _procedural(tmp_path / "pre", ["cabinet", "chair"], 3, 0.34)
    args = _args(checkpoint, tiny_dataset, tiny_dataset, tmp_path / "weights")
    assert ship_model.main([*args, "--pretrain-data", str(pretrain)]) == 0

    shipped = tmp_path / "weights" / "tiny.safetensors"
    _, card = read_metadata(shipped)
    assert (card["summary"], card["recipe"]) == ("a tiny model", "pfnet train ...")
    train = read_manifest(tiny_dataset)["splits"]["train"]["total"]
    assert card["train_data"]["shapes"] == train == 24
    assert card["train_data"]["source"]["format"] == "procedural"
    assert card["pretrain_data"] == {
        "source": {"format": "procedural", "path": None},
        "shapes": read_manifest(pretrain)["splits"]["train"]["total"],
        "categories": ["cabinet", "chair"],
        "licenses": [],
    }
    # the figures are those of the float16 file itself on the test split, 25 % missing
    predict_split(shipped, tiny_dataset, tmp_path / "pred", device="cpu")
    mean = evaluate_predictions(tmp_path / "pred", tiny_dataset, missing_ratio=0.25).report["mean"]
    assert card["test"]["cd_l2"] == pytest.approx(mean["pred_to_gt"] + mean["gt_to_pred"])
    assert card["test"]["f_score"] == pytest.approx(mean["f_score"])
    assert card["test"]["data"].startswith("tiny test split (12 shapes, never trained on)")


def test_without_pretraining_the_card_names_none(ship_model, checkpoint, tiny_dataset, tmp_path):
    assert ship_model.main(_args(checkpoint, tiny_dataset, tiny_dataset, tmp_path)) == 0
    _, card = read_metadata(tmp_path / "tiny.safetensors")
    assert "pretrain_data" not in card
    assert json.dumps(card)  # JSON-serialisable as written


def test_a_test_split_the_model_trained_on_is_refused(ship_model, checkpoint, tmp_path):
    # the same seeded shapes split another way: some test shapes are the other's train shapes
    train = _procedural(tmp_path / "a", ["chair"], 8, 0.25)
    test = _procedural(tmp_path / "b", ["chair"], 8, 0.75)
    with pytest.raises(SystemExit, match=r"refusing: \d+ test shapes were trained on, e\.g\."):
        ship_model.main(_args(checkpoint, train, test, tmp_path / "weights"))
    assert not (tmp_path / "weights").exists()


def test_the_card_leads_with_the_scan_protocol_and_pfnet_models_shows_it(
    ship_model, checkpoint, tiny_dataset, tmp_path, capsys, monkeypatch
):
    def table(cd, f):
        return {
            "mean": {"cd_l2": cd, "f_score": f},
            "categories": {"chair": {"cd_l2": cd, "f_score": f}},
        }

    scan = tmp_path / "scan-y.json"
    scan.write_text(
        json.dumps(
            {
                "data": "data/sh3d", "split": "test", "missing_ratio": 0.25, "up": "y",
                "f_wins_over_mirror": 1, "mirror_fill": 0.15,
                "results": {
                    "complete (scan protocol)": table(12.5, 0.04),
                    "same model, shape frame (paper protocol)": table(9.0, 0.03),
                    "mirror of the input (learns nothing)": table(290.0, 0.034),
                },
            }
        )
    )  # fmt: skip
    args = _args(checkpoint, tiny_dataset, tiny_dataset, tmp_path / "weights")
    assert ship_model.main([*args, "--scan-protocol", str(scan)]) == 0
    _, card = read_metadata(tmp_path / "weights" / "tiny.safetensors")
    assert list(card)[:3] == ["summary", "scan", "recipe"]
    (first,) = card["scan"]
    assert first["cd_l2"] == 12.5 and first["mirror"] == {"cd_l2": 290.0, "f_score": 0.034}
    assert first["mirror_fill"] == 0.15
    assert "y-up, through pfnet complete" in first["data"]
    import argparse
    from types import SimpleNamespace

    import pfnet.inference.shipped
    from pfnet.commands import models

    fake = SimpleNamespace(name="tiny", card=card, config={"frame": "scan"}, size_mb=1.0)
    monkeypatch.setattr(pfnet.inference.shipped, "shipped_models", lambda: [fake])
    capsys.readouterr()
    assert models.run(argparse.Namespace(json=False)) == 0
    said = capsys.readouterr().out
    assert "frame     scan: trained on partials in their own centroid" in said
    assert said.index("scans") < said.index("paper")
    assert "12.50" in said and "a mirror of the input: 290.00, 0.034" in said
    assert "through pfnet complete (mirror fill 0.15)" in said
    del card["scan"][0]["mirror_fill"]  # a card from before the mirror fill
    assert models.run(argparse.Namespace(json=False)) == 0
    assert "(the network's points, --mirror-fill 0)" in capsys.readouterr().out
