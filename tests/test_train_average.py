"""The exponential moving average of a generator's weights against its formula."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from torch import nn  # noqa: E402

from pfnet.training.average import WeightAverage  # noqa: E402


def _network(value: float) -> nn.Sequential:
    network = nn.Sequential(nn.Linear(2, 2), nn.BatchNorm1d(2))
    with torch.no_grad():
        for tensor in network.state_dict().values():
            if tensor.is_floating_point():
                tensor.fill_(value)
    return network


def test_the_average_follows_its_formula_with_the_warm_up_of_its_decay() -> None:
    live = _network(1.0)
    average = WeightAverage(live, decay=0.5)
    expected = 1.0
    for step in range(1, 13):
        value = float(step * step)
        live.load_state_dict(_network(value).state_dict())
        live[1].num_batches_tracked.fill_(step)
        average.update(live)
        keep = min(0.5, (1 + step) / (10 + step))  # the naive formula, step by step
        expected = keep * expected + (1 - keep) * value
        for name, tensor in average.model.state_dict().items():
            if tensor.is_floating_point():
                torch.testing.assert_close(tensor, torch.full_like(tensor, expected), msg=name)
        assert int(average.model[1].num_batches_tracked) == step  # counters are copied
    assert average.decay_at(8) == 0.5 and average.decay_at(7) == pytest.approx(8 / 17)
    assert not average.model.training
    assert not any(p.requires_grad for p in average.model.parameters())


def test_reset_and_state_round_trip() -> None:
    live = _network(3.0)
    average = WeightAverage(_network(0.0), decay=0.9)
    average.update(live)
    copy = WeightAverage(_network(7.0), decay=0.9)
    copy.load_state_dict(average.state_dict())
    assert copy.updates == 1
    for name, tensor in average.model.state_dict().items():
        assert torch.equal(copy.model.state_dict()[name], tensor), name
    average.reset(live)
    assert average.updates == 0
    assert torch.equal(average.model[0].weight, live[0].weight)
    for bad in (0.0, 1.0, -0.5):
        with pytest.raises(ValueError, match="decay must be in"):
            WeightAverage(live, bad)
