"""Start a wider PF-Net generator from a trained narrower one, computing the same function.

``pfnet train --width 0.5 --init-from sh3d-mirror`` (a width-0.25 model) grows every hidden
layer of the trained generator ``k`` times (``k`` = the ratio of the widths, a whole number):
each hidden unit of the wide network is a copy of a unit of the trained one (unit ``i`` of a
layer copies unit ``i mod n`` of the trained layer of ``n``), and each weight that reads a
copied unit is the trained weight times a share, the shares of a unit's ``k`` copies summing
to one. The wide network computes what the trained one does, in training mode as in
evaluation mode: every BatchNorm channel of a copy sees the statistics of its original, and
the encoder's fusing BatchNorm, which normalises over all the latent's features, sees every
value ``k`` times. The shares are drawn at random, so that the copies receive different
gradients and grow apart (equal shares would keep them equal forever).

The idea is Net2WiderNet (Chen, Goodfellow and Shlens, "Net2Net", ICLR 2016), with random
shares instead of added noise so that the start is exact; not part of PF-Net. It answers
"would a wider network do better?" on a CPU without training the wide one from nothing.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from pfnet.errors import ConfigError

# the decoder's first layer reads the latent: the CMLP's last four layers' max-pools, each
# block copied within itself
LATENT_READER = "decoder.fc1.weight"
# the CMLP layers whose max-pools make the latent, in the latent's order (CMLP.forward)
LATENT_LAYERS = (5, 4, 3, 2)


def _latent_blocks(state: dict[str, Tensor]) -> list[int]:
    """Sizes of the latent's blocks in a PF-Net-family generator's ``state``."""
    return [
        state[f"encoder.cmlps.0.mlp.layers.{layer}.0.weight"].shape[0] for layer in LATENT_LAYERS
    ]


def _copied(new: int, old: int, key: str, dim: int) -> Tensor:
    """Index of the trained unit each of ``new`` units copies (``i mod old``)."""
    if new % old:
        raise ConfigError(
            f"cannot widen weight {key}: {old} units along dimension {dim} do not go into "
            f"{new} (the widths must be in a whole ratio, e.g. 0.25 to 0.5 or 1.0)"
        )
    return torch.arange(new) % old


def _latent_copied(new_blocks: list[int], old_blocks: list[int]) -> Tensor:
    """Index of the trained latent feature each wide latent feature copies, block by block."""
    index, start = [], 0
    for new, old in zip(new_blocks, old_blocks, strict=True):
        index.append(start + _copied(new, old, LATENT_READER, 1))
        start += old
    return torch.cat(index)


def _shares(index: Tensor, rows: int, generator: torch.Generator) -> Tensor:
    """``(rows, len(index))`` random positive shares, those of the copies of one trained
    unit (equal ``index``) summing to one in every row."""
    draws = torch.rand(rows, len(index), generator=generator, dtype=torch.float64) + 0.5
    totals = torch.zeros(rows, int(index.max()) + 1, dtype=torch.float64)
    totals.index_add_(1, index, draws)
    return draws / totals[:, index]


def widened_state(trained: dict[str, Tensor], wide: nn.Module, seed: int = 0) -> dict[str, Tensor]:
    """The state of ``wide`` (a PF-Net-family generator of the trained one's model, k times as
    wide) that computes what the generator of state ``trained`` does.

    Raises:
        ConfigError: ``wide`` is not such a network: a weight it lacks or has in a size that
            is not a whole multiple of the trained one's.
    """
    target = wide.state_dict()
    missing = sorted(set(trained) ^ set(target))
    if missing or LATENT_READER not in target:
        raise ConfigError(
            "only a PF-Net-family generator can be widened from one of its own model"
            + (f" (weight {missing[0]} is in one of the two only)" if missing else "")
        )
    generator = torch.Generator().manual_seed(seed)
    latent = _latent_copied(_latent_blocks(target), _latent_blocks(trained))
    state = {}
    for key, value in trained.items():
        shape = target[key].shape
        if value.ndim != len(shape):
            raise ConfigError(f"cannot widen weight {key}: {tuple(value.shape)} to {tuple(shape)}")
        index = [
            latent
            if key == LATENT_READER and dim == 1
            else _copied(shape[dim], value.shape[dim], key, dim)
            for dim in range(value.ndim)
        ]
        grown = value
        for dim, copied in enumerate(index):
            grown = grown.index_select(dim, copied)
        # a Linear's or Conv1d's input units: the copies of one trained unit share its weight
        if value.ndim >= 2 and shape[1] != value.shape[1]:
            shares = _shares(index[1], shape[0], generator).to(grown.dtype)
            grown = grown * shares.reshape(*shares.shape, *([1] * (value.ndim - 2)))
        state[key] = grown.clone()
    return state
