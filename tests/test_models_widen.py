"""Widening a trained PF-Net generator (pfnet.models.widen): the wide network computes the
narrow one's completions in both modes, its copies grow apart in training, and fine-tuning's
init_from starts a wider run from a narrower checkpoint and refuses other widths."""

from __future__ import annotations

from dataclasses import asdict

import pytest

torch = pytest.importorskip("torch")

from pfnet.errors import ConfigError  # noqa: E402
from pfnet.models import ModelConfig, build_model  # noqa: E402
from pfnet.models.widen import widened_state  # noqa: E402


def _trained(model: str, width: float) -> torch.nn.Module:
    """A generator with random weights and BatchNorm statistics of its own."""
    torch.manual_seed(0)
    generator = build_model(ModelConfig(model=model, n_points=256, missing_ratio=0.5, width=width))
    generator.train()
    with torch.no_grad():
        for _ in range(3):
            generator(torch.randn(4, 128, 3))
    return generator


def _wide(narrow: torch.nn.Module, model: str, width: float, seed: int = 1) -> torch.nn.Module:
    wide = build_model(ModelConfig(model=model, n_points=256, missing_ratio=0.5, width=width))
    wide.load_state_dict(widened_state(narrow.state_dict(), wide, seed=seed))
    return wide


@pytest.mark.parametrize("model", ["pfnet-vanilla", "pfnet-mirror"])
@pytest.mark.parametrize("factor", [2, 4])
def test_a_widened_generator_completes_as_the_trained_one_in_both_modes(model, factor):
    narrow = _trained(model, 0.125)
    wide = _wide(narrow, model, 0.125 * factor)
    assert sum(p.numel() for p in wide.parameters()) > 3 * sum(
        p.numel() for p in narrow.parameters()
    )
    partial = torch.randn(3, 160, 3)
    for mode in ("eval", "train"):  # train: every BatchNorm on the batch's own statistics
        narrow.train(mode == "train")
        wide.train(mode == "train")
        with torch.no_grad():
            expected, got = narrow(partial), wide(partial)
        for stage in ("primary", "secondary", "detail"):
            torch.testing.assert_close(
                getattr(got, stage), getattr(expected, stage), atol=1e-5, rtol=1e-4
            )


def test_the_copies_of_a_unit_grow_apart_in_training():
    narrow = _trained("pfnet-vanilla", 0.125)
    wide = _wide(narrow, "pfnet-vanilla", 0.25)
    first = "encoder.cmlps.0.mlp.layers.0.0.weight"  # reads xyz; 8 trained units, 16 wide
    before = wide.state_dict()[first].clone()
    torch.testing.assert_close(before[8:], before[:8])  # a copy's input weights: its original's
    optimiser = torch.optim.SGD(wide.parameters(), lr=0.1)
    wide.train()
    loss = wide(torch.randn(4, 128, 3)).detail.square().mean()
    loss.backward()
    optimiser.step()
    after = wide.state_dict()[first]
    assert not torch.allclose(after[8:], after[:8], atol=1e-7)


def test_equal_shares_are_not_drawn_and_another_seed_draws_others():
    narrow = _trained("pfnet-vanilla", 0.125)
    key = "decoder.fc2.weight"
    one = _wide(narrow, "pfnet-vanilla", 0.25, seed=1).state_dict()[key]
    other = _wide(narrow, "pfnet-vanilla", 0.25, seed=2).state_dict()[key]
    trained = narrow.state_dict()[key]  # (64, 128): (128, 256) wide
    assert not torch.allclose(one, trained.repeat(2, 2) / 2)
    assert not torch.allclose(one, other)
    # the two copies of each trained input unit still add up to its weight
    torch.testing.assert_close(one[:, :128] + one[:, 128:], trained.repeat(2, 1))


def test_only_a_pfnet_family_generator_of_a_whole_ratio_is_widened():
    mlp = build_model(ModelConfig(model="mlp", n_points=256, missing_ratio=0.5, width=0.125))
    wide_mlp = build_model(ModelConfig(model="mlp", n_points=256, missing_ratio=0.5, width=0.25))
    with pytest.raises(ConfigError, match="only a PF-Net-family generator"):
        widened_state(mlp.state_dict(), wide_mlp)
    narrow = _trained("pfnet-vanilla", 0.125)
    odd = build_model(
        ModelConfig(model="pfnet-vanilla", n_points=256, missing_ratio=0.5, width=0.1875)
    )
    with pytest.raises(ConfigError, match=r"widen weight .*: 128 units along dimension 1 do not"):
        widened_state(narrow.state_dict(), odd)


def test_fine_tuning_widens_a_narrower_checkpoint_and_refuses_other_widths(tmp_path):
    from pfnet.inference.checkpoint import save_checkpoint
    from pfnet.training.config import TrainConfig
    from pfnet.training.resume import start_from

    sizes = dict(n_points=256, missing_ratio=0.5)
    narrow = _trained("pfnet-vanilla", 0.125)
    path = tmp_path / "narrow.pt"
    config = asdict(TrainConfig(model="pfnet-vanilla", **sizes, width=0.125))
    save_checkpoint(path, {"model": narrow.state_dict(), "config": config})
    partial = torch.randn(2, 160, 3)
    narrow.eval()
    for model in ("pfnet-vanilla", "pfnet-mirror"):  # the mirror model grows from it too
        wide = build_model(ModelConfig(model=model, **sizes, width=0.5))
        start_from(wide, TrainConfig(model=model, **sizes, width=0.5, init_from=str(path)))
        assert wide.state_dict()["decoder.fc1.weight"].shape == (512, 960)
        if model == "pfnet-vanilla":
            wide.eval()
            with torch.no_grad():
                torch.testing.assert_close(
                    wide(partial).detail, narrow(partial).detail, atol=1e-5, rtol=1e-4
                )
    for width in (0.1875, 0.0625):  # not a whole multiple; narrower
        generator = build_model(ModelConfig(model="pfnet-vanilla", **sizes, width=width))
        with pytest.raises(ConfigError, match=rf"another network: width 0.125 \(run: {width}\)"):
            start_from(
                generator,
                TrainConfig(model="pfnet-vanilla", **sizes, width=width, init_from=str(path)),
            )
