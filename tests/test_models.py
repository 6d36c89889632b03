"""Shapes, forward/backward and batch-of-one behaviour of every completion model."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from pfnet.errors import ConfigError  # noqa: E402
from pfnet.geometry import farthest_point_sample  # noqa: E402
from pfnet.models import (  # noqa: E402
    CMLP,
    MODEL_NAMES,
    MODELS,
    Completion,
    CompletionModel,
    Discriminator,
    ModelConfig,
    MultiResolutionEncoder,
    PFNet,
    PointPyramidDecoder,
    build_model,
    initialise,
)
from pfnet.models.layers import BatchNormFC, multi_resolution_indices  # noqa: E402
from pfnet.training.config import TrainConfig  # noqa: E402

WIDTH = 0.125  # narrow networks keep these tests fast; the paper width is checked once below


@pytest.fixture(autouse=True)
def _seed() -> None:
    torch.manual_seed(0)


@pytest.mark.parametrize("name", sorted(MODELS))
@pytest.mark.parametrize("batch, n_partial", [(3, 384), (1, 384), (2, 131)])
def test_every_model_output_shapes(name: str, batch: int, n_partial: int) -> None:
    model = MODELS[name](n_points=512, n_missing=128, width=WIDTH)
    out = model(torch.rand(batch, n_partial, 3) * 2 - 1)
    assert isinstance(out, Completion)
    assert out.detail.shape == (batch, 128, 3)
    assert model.n_missing == 128 and model.n_points == 512
    if model.multi_stage:
        assert out.primary.shape == (batch, 64, 3)
        assert out.secondary.shape == (batch, 128, 3)
    else:
        assert out.primary is None and out.secondary is None


@pytest.mark.parametrize("name", sorted(MODELS))
def test_every_model_forward_backward_in_train_mode_with_batch_of_one(name: str) -> None:
    model = MODELS[name](n_points=512, n_missing=256, width=WIDTH).train()
    for batch in (4, 1):  # a last batch of one crashes the authors' code
        model.zero_grad()
        out = model(torch.rand(batch, 256, 3))
        loss = sum(t.square().mean() for t in out if t is not None)
        loss.backward()
        grads = [p.grad for p in model.parameters() if p.requires_grad]
        assert all(g is not None and torch.isfinite(g).all() for g in grads)
        assert any(g.abs().sum() > 0 for g in grads)


def test_paper_width_pfnet_matches_the_authors_sizes() -> None:
    model = PFNet(n_points=2048, n_missing=512, width=1.0).eval()
    assert model.encoder.out_features == 1920
    assert model.decoder.fc1.in_features == 1920
    assert model.decoder.detail_fc.out_features == 128 * 512  # the authors' fc1_1
    assert model.decoder.secondary_fc.out_features == 64 * 128  # fc2_1
    assert model.decoder.detail_conv[-1].out_channels == 3 * 512 // 128  # conv1_3: 12
    with torch.no_grad():
        out = model(torch.rand(2, 1536, 3))
    assert out.detail.shape == (2, 512, 3)


def test_cmlp_concatenates_the_last_four_max_pooled_layers() -> None:
    cmlp = CMLP(width=1.0)
    assert cmlp.out_features == 128 + 256 + 512 + 1024
    assert cmlp(torch.rand(2, 50, 3)).shape == (2, 1920)


def _conv_widths(module: torch.nn.Module) -> list[int]:
    return [m.out_channels for m in module.modules() if isinstance(m, torch.nn.Conv1d)]


def test_cmlp_layers_are_the_authors_in_each_model() -> None:
    # PF-Net's encoder (model_PFNet.py Convlayer): six layers; the CMLP baseline
    # (CMLP_autoencoder) and the paper (§3.1): five. Both pool 128 + 256 + 512 + 1024.
    encoder = [64, 64, 128, 256, 512, 1024]
    pfnet = PFNet(n_points=512, n_missing=128)
    assert all(_conv_widths(cmlp) == encoder for cmlp in pfnet.encoder.cmlps)
    mr_cmlp = MODELS["mr-cmlp"](n_points=512, n_missing=128)
    assert all(_conv_widths(cmlp) == encoder for cmlp in mr_cmlp.encoder.cmlps)
    cmlp = MODELS["cmlp"](n_points=512, n_missing=128)
    assert _conv_widths(cmlp.encoder) == [64, 128, 256, 512, 1024]
    assert cmlp.encoder.out_features == 1920 and cmlp.decoder.layers[0][0].in_features == 1920
    assert _conv_widths(MODELS["mlp"](n_points=512, n_missing=128).encoder) == encoder[1:]


def test_decoder_builds_detail_around_secondary_and_secondary_around_primary() -> None:
    decoder = PointPyramidDecoder(in_features=32, n_missing=256, width=WIDTH).eval()
    out = decoder(torch.rand(2, 32))
    # Each primary centre owns 2 consecutive secondary points, each secondary point owns
    # M / 128 consecutive detail points: zeroing the offset convs collapses them onto centres.
    with torch.no_grad():
        decoder.secondary_conv.weight.zero_()
        decoder.secondary_conv.bias.zero_()
        decoder.detail_conv[-1].weight.zero_()
        decoder.detail_conv[-1].bias.zero_()
        out = decoder(torch.rand(2, 32))
    assert torch.equal(out.secondary, out.primary.repeat_interleave(2, dim=1))
    assert torch.equal(out.detail, out.secondary.repeat_interleave(2, dim=1))


def test_encoder_scales_are_ifps_prefixes_of_the_partial_cloud() -> None:
    rng = np.random.default_rng(0)
    partial = rng.random((2, 301, 3), dtype=np.float32)
    index = multi_resolution_indices(partial)
    assert index.shape == (2, 150)
    np.testing.assert_array_equal(index[:, :75], farthest_point_sample(partial, 75))
    encoder = MultiResolutionEncoder(width=WIDTH).eval()
    tensor = torch.from_numpy(partial)
    with torch.no_grad():
        implicit = encoder(tensor)
        explicit = encoder(tensor, torch.from_numpy(index))
    torch.testing.assert_close(implicit, explicit, rtol=0, atol=0)


def test_model_output_does_not_depend_on_the_order_of_the_input_points() -> None:
    model = PFNet(n_points=512, n_missing=128, width=WIDTH).eval()
    partial = torch.rand(1, 200, 3)
    perm = torch.randperm(200)
    with torch.no_grad():
        a = model(partial).detail
        # IFPS starts at index 0, so put the same first point first in both orders.
        perm = torch.cat([torch.tensor([0]), perm[perm != 0]])
        b = model(partial[:, perm]).detail
    torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def test_discriminator_returns_one_logit_per_cloud_and_accepts_a_batch_of_one() -> None:
    disc = Discriminator(width=WIDTH).train()
    assert disc(torch.rand(5, 128, 3)).shape == (5,)
    logits = disc(torch.rand(1, 128, 3))
    assert logits.shape == (1,)
    logits.sum().backward()
    full = Discriminator(width=1.0)
    assert full.head[0].in_features == 448


def test_batch_norm_fc_uses_running_statistics_for_a_batch_of_one() -> None:
    bn = BatchNormFC(3).train()
    bn(torch.randn(8, 3) * 4 + 2)
    mean, var = bn.running_mean.clone(), bn.running_var.clone()
    x = torch.randn(1, 3)
    out = bn(x)
    torch.testing.assert_close(out, (x - mean) / torch.sqrt(var + bn.eps))
    assert torch.equal(bn.running_mean, mean)  # not updated by the batch of one


def test_build_model_from_config() -> None:
    config = TrainConfig(model="mr-cmlp", n_points=512, width=WIDTH)
    model = build_model(config)
    assert type(model) is MODELS["mr-cmlp"]
    assert model.n_missing == config.n_missing == 128


def test_build_model_errors() -> None:
    with pytest.raises(ConfigError, match="n_points is not set"):
        build_model(TrainConfig(model="pfnet"))
    with pytest.raises(ConfigError, match="multiple of 128"):
        build_model(TrainConfig(model="pfnet", n_points=1000, width=WIDTH))
    with pytest.raises(ConfigError, match="not a positive multiple of 128"):
        PointPyramidDecoder(in_features=8, n_missing=64)


@pytest.mark.parametrize(
    "shape, match",
    [
        ((2, 10), r"shape \(B, n, 3\)"),
        ((2, 10, 2), r"shape \(B, n, 3\)"),
        ((2, 3, 3), "at least 4"),
    ],
)
def test_bad_partial_shapes_are_rejected(shape: tuple[int, ...], match: str) -> None:
    model = PFNet(n_points=512, n_missing=128, width=WIDTH)
    with pytest.raises(ValueError, match=match):
        model(torch.rand(*shape))


def test_integer_partial_and_bad_scale_indices_are_rejected() -> None:
    model = PFNet(n_points=512, n_missing=128, width=WIDTH)
    with pytest.raises(ValueError, match="float tensor"):
        model(torch.ones(1, 20, 3, dtype=torch.int64))
    with pytest.raises(ValueError, match=r"scale_indices must have shape \(1, 10\)"):
        model(torch.rand(1, 20, 3), torch.zeros(1, 5, dtype=torch.int64))


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_every_registered_model_declares_its_capabilities(name: str) -> None:
    cls = MODELS[name]
    assert issubclass(cls, CompletionModel)
    flags = (cls.adversarial, cls.multi_resolution, cls.multi_stage)
    assert all(isinstance(flag, bool) for flag in flags)
    assert cls.adversarial == (name == "pfnet")
    assert cls.multi_stage == name.startswith("pfnet")
    assert cls.multi_resolution == (
        name in ("pfnet", "pfnet-vanilla", "pfnet-mirror", "pfnet-edge", "mr-cmlp")
    )


def _layers(module: torch.nn.Module, kinds: tuple[type, ...]) -> list[torch.nn.Module]:
    return [m for m in module.modules() if isinstance(m, kinds)]


def test_authors_initialisation_statistics() -> None:
    # Train_PFNet.py's weights_init_normal, applied to generator and discriminator alike.
    for module in (PFNet(n_points=2048, n_missing=512, width=0.5), Discriminator(width=1.0)):
        before = {k: v.clone() for k, v in module.state_dict().items()}
        initialise(module, "authors")
        big = [c.weight for c in _layers(module, (torch.nn.Conv1d,)) if c.weight.numel() > 30_000]
        assert big
        for weight in big:
            assert abs(weight.std().item() - 0.02) < 0.001 and abs(weight.mean().item()) < 0.001
        norms = _layers(module, (torch.nn.BatchNorm1d,))  # BatchNormFC included
        weights = torch.cat([n.weight for n in norms])
        assert abs(weights.mean().item() - 1) < 0.005 and 0.01 < weights.std().item() < 0.03
        assert all(torch.equal(n.bias, torch.zeros_like(n.bias)) for n in norms)
        # Fully connected layers and convolution biases keep PyTorch's values, as theirs do.
        after = module.state_dict()
        for name, linear in module.named_modules():
            if isinstance(linear, torch.nn.Linear):
                assert torch.equal(after[f"{name}.weight"], before[f"{name}.weight"])
            if isinstance(linear, torch.nn.Conv1d):
                assert torch.equal(after[f"{name}.bias"], before[f"{name}.bias"])


def test_pytorch_initialisation_is_what_build_model_gives() -> None:
    config = ModelConfig(model="pfnet", n_points=512, width=WIDTH)
    torch.manual_seed(3)
    plain = build_model(config).state_dict()
    torch.manual_seed(3)
    model = initialise(build_model(config), "pytorch")
    assert all(torch.equal(v, plain[k]) for k, v in model.state_dict().items())
    with pytest.raises(ConfigError, match="init must be one of pytorch, authors"):
        initialise(model, "xavier")


@pytest.mark.parametrize("init", ["pytorch", "authors"])
def test_training_step_initialises_generator_and_discriminator(init: str) -> None:
    from pfnet.training.config import TrainConfig
    from pfnet.training.distributed import DistContext
    from pfnet.training.step import TrainingStep

    config = TrainConfig(model="pfnet", n_points=512, width=WIDTH, init=init)
    step = TrainingStep(config, DistContext(0, 1, 0, torch.device("cpu")))
    for module in (step.generator, step.discriminator):
        weights = torch.cat([n.weight for n in _layers(module, (torch.nn.BatchNorm1d,))])
        assert torch.all(weights == 1) == (init == "pytorch")


def test_the_detail_head_resized_to_another_missing_ratio_repeats_the_trained_offsets():
    from pfnet.models.pfnet import PFNetVanilla, resized_detail_head

    torch.manual_seed(0)
    trained = PFNetVanilla(n_points=512, n_missing=128, width=0.125).eval()
    partial = torch.rand(2, 384, 3)
    before = trained(partial).detail.reshape(2, 128, 1, 3)  # one offset per secondary centre
    for n_missing, offsets in ((384, [0, 0, 0]), (128, [0])):
        resized = PFNetVanilla(n_points=512, n_missing=n_missing, width=0.125).eval()
        resized.load_state_dict(resized_detail_head(trained.state_dict(), n_missing))
        after = resized(partial).detail.reshape(2, 128, len(offsets), 3)
        torch.testing.assert_close(after, before[:, :, offsets])
    wider = PFNetVanilla(n_points=512, n_missing=256, width=0.125)
    state = resized_detail_head(wider.state_dict(), 128)  # a smaller M keeps the first offsets
    torch.testing.assert_close(
        state["decoder.detail_conv.4.bias"], wider.decoder.detail_conv[4].bias[:3]
    )
    with pytest.raises(ConfigError, match="M = 200 is not a positive multiple of 128"):
        resized_detail_head(trained.state_dict(), 200)


def test_fine_tuning_starts_a_pfnet_at_another_missing_ratio_but_not_a_baseline(tmp_path):
    from dataclasses import asdict

    from pfnet.inference.checkpoint import save_checkpoint
    from pfnet.training.resume import start_from

    def checkpoint(model: str) -> str:
        generator = build_model(
            ModelConfig(model=model, n_points=512, missing_ratio=0.5, width=0.125)
        )
        path = tmp_path / f"{model}.pt"
        config = asdict(TrainConfig(model=model, n_points=512, missing_ratio=0.5, width=0.125))
        save_checkpoint(path, {"model": generator.state_dict(), "config": config})
        return str(path)

    sizes = dict(n_points=512, missing_ratio=0.25, width=0.125)  # 128 points where 256 were
    for model, source in (("pfnet-vanilla", "pfnet-vanilla"), ("pfnet-mirror", "pfnet-vanilla")):
        generator = build_model(ModelConfig(model=model, **sizes))
        path = checkpoint(source)
        start_from(generator, TrainConfig(model=model, **sizes, init_from=path))
        trained = torch.load(path, weights_only=False)["model"]
        torch.testing.assert_close(
            generator.state_dict()["decoder.detail_conv.4.weight"],
            trained["decoder.detail_conv.4.weight"][:3],  # 2 offsets per centre cut to the first
        )
    baseline = build_model(ModelConfig(model="mlp", **sizes))
    with pytest.raises(ConfigError, match=r"another network: missing_ratio 0.5 \(run: 0.25\)"):
        start_from(baseline, TrainConfig(model="mlp", **sizes, init_from=checkpoint("mlp")))
