"""ModelConfig, the one registry of models, and what inference may import (no torch needed)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from pfnet.errors import ConfigError
from pfnet.models import MODEL_NAMES, MODEL_TITLES, PAPER_MODELS, REGISTRY, ModelConfig
from pfnet.training.config import PRESETS, TrainConfig


def _modules_after(code: str) -> list[str]:
    """The ``pfnet.*`` and ``torch`` modules a fresh interpreter holds after running ``code``."""
    script = (
        f"{code}\nimport json, sys\n"
        "print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in "
        "('pfnet', 'torch'))))"
    )
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=True
    )
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_inference_never_imports_training() -> None:
    pytest.importorskip("torch")
    loaded = _modules_after(
        "import pfnet.inference.checkpoint, pfnet.inference.shipped, pfnet.inference.predict\n"
        "from pfnet.models import CMLP, MODELS, PFNet, build_model, initialise\n"
        "from pfnet.inference.checkpoint import load_checkpoint\n"
        "load_checkpoint(None)"
    )
    assert "pfnet.models.pfnet" in loaded  # the import did happen
    assert not [m for m in loaded if m.startswith("pfnet.training")]


def test_model_list_and_configs_need_no_torch() -> None:
    loaded = _modules_after(
        "import pfnet.models, pfnet.training.config, pfnet.study.paper\n"
        "pfnet.training.config.TrainConfig(n_points=2048).model_config()"
    )
    assert "pfnet.models.registry" in loaded and "torch" not in loaded


def test_one_list_of_models_in_the_papers_order() -> None:
    assert MODEL_NAMES == tuple(REGISTRY)
    assert PAPER_MODELS == ("pfnet", "pfnet-vanilla", "mr-cmlp", "cmlp", "mlp")
    assert set(MODEL_NAMES) - set(PAPER_MODELS) == {"pfnet-mirror", "pfnet-edge"}
    assert MODEL_TITLES["pfnet-vanilla"] == "PF-Net (vanilla)"
    from pfnet.study import STUDY_MODELS
    from pfnet.study.paper import PAPER_ORDER

    assert STUDY_MODELS == PAPER_ORDER == PAPER_MODELS
    with pytest.raises(
        ConfigError, match="model must be one of pfnet, pfnet-vanilla, pfnet-mirror"
    ):
        ModelConfig(model="pointnet")


def test_model_config_is_the_networks_part_of_a_train_config() -> None:
    train = PRESETS["small"].replace(n_points=512, model="cmlp", seed=4)
    assert isinstance(train, ModelConfig)
    model = train.model_config()
    assert type(model) is ModelConfig
    assert model == ModelConfig(
        model="cmlp", n_points=512, missing_ratio=0.25, width=0.25, frame="scan"
    )
    assert model.n_missing == 128
    # A checkpoint stores the training config; inference reads the network's keys of it.
    assert ModelConfig.from_dict(train.to_dict(), extra="ignore") == model
    with pytest.raises(
        ConfigError,
        match="checkpoint x: unknown key.*seed.*; valid keys: model, n_points, missing_ratio, "
        "width, frame$",
    ):
        ModelConfig.from_dict(train.to_dict(), source="checkpoint x")
    with pytest.raises(ConfigError, match="checkpoint x: n_points must be an integer"):
        ModelConfig.from_dict({"n_points": 10**12, "lr": 1}, source="checkpoint x", extra="ignore")
    with pytest.raises(ConfigError, match="removes 6 points; at least 1 must be missing"):
        ModelConfig(n_points=8, missing_ratio=0.7)


def test_init_key_defaults_to_pytorch_for_configs_written_before_it() -> None:
    assert (PRESETS["paper"].init, PRESETS["small"].init) == ("authors", "pytorch")
    old = PRESETS["paper"].replace(n_points=2048).to_dict()
    del old["init"]  # a config.json or checkpoint of an earlier pfnet
    assert TrainConfig.from_dict(old).init == "pytorch"
    assert TrainConfig.from_dict(json.loads(json.dumps(old))).replace(init="authors").init == (
        "authors"
    )
    with pytest.raises(ConfigError, match="init must be one of pytorch, authors; got 'xavier'"):
        TrainConfig(init="xavier")


def test_the_shipped_models_config_loads_as_both_configs() -> None:
    from pfnet.inference.shipped import shipped_models

    (shipped,) = [m for m in shipped_models() if m.name == "sh3d-small"]
    train = TrainConfig.from_dict(shipped.config)
    assert (train.model, train.init, train.preset) == ("pfnet-vanilla", "pytorch", "small")
    assert ModelConfig.from_dict(shipped.config, extra="ignore") == train.model_config()
    # A config written before the `init` key existed starts as PyTorch's defaults did.
    before = {key: value for key, value in shipped.config.items() if key != "init"}
    assert TrainConfig.from_dict(before) == train
