"""PF-Net: multi-resolution encoder, point pyramid decoder and discriminator (paper §3).

Layer sizes follow the paper and the authors' code (DESIGN.md §4) at ``width = 1``; a smaller
``width`` scales every hidden layer for quick CPU training.

The encoder's input differs from the authors' on purpose. Their network always sees 2048
slots: the partial cloud plus the cropped points moved to the origin (zero-filled), and
the coarser scales are IFPS samples (1024, 512) of that padded cloud. Here the encoder takes
the partial cloud itself, with any number of points n, and its three scales are IFPS
samples of n, n // 2 and n // 4 points (k = 2). Max-pooling makes every layer independent of
n, so one trained network accepts any partial size, and no phantom points at the origin
leak into the features. A checkpoint trained by the authors' code cannot be loaded here.
"""

from __future__ import annotations

from typing import ClassVar

import torch
from torch import Tensor, nn

from pfnet.errors import ConfigError
from pfnet.models.completion import Completion, CompletionModel
from pfnet.models.layers import (
    BatchNormFC,
    PointMLP,
    check_partial,
    gather_points,
    multi_resolution_indices,
    scaled,
)

PRIMARY_POINTS = 64  # M1 (paper §4: "we set M1 = 64, M2 = 128")
SECONDARY_POINTS = 128  # M2
N_SCALES = 3  # scales of the multi-resolution encoder (k = 2: n, n/2, n/4)
# The CMLP's layers. The paper gives [64-128-256-512-1024] (§3.1), as the authors' CMLP
# baseline has it; the CMLPs of their PF-Net encoder (model_PFNet.py) have one more 64 layer.
ENCODER_CMLP_CHANNELS = (64, 64, 128, 256, 512, 1024)
BASELINE_CMLP_CHANNELS = (64, 128, 256, 512, 1024)


class CMLP(nn.Module):
    """Combined multi-layer perceptron (paper §3.1, Fig. 4b).

    A shared per-point MLP (BN + ReLU); the last four layers, 128, 256, 512 and 1024 wide, are
    max-pooled over the points and concatenated into a 1920-d vector.

    Args:
        width: Multiplier of every layer's channels (1.0 = the paper's).
        channels: The layers' widths at ``width = 1``: :data:`ENCODER_CMLP_CHANNELS`
            (3→64→64→128→256→512→1024, PF-Net's encoder) or :data:`BASELINE_CMLP_CHANNELS`
            (3→64→128→256→512→1024, the CMLP baseline).
    """

    def __init__(
        self, width: float = 1.0, channels: tuple[int, ...] = ENCODER_CMLP_CHANNELS
    ) -> None:
        super().__init__()
        channels = [scaled(c, width) for c in channels]
        self.mlp = PointMLP(channels)
        self.out_features = sum(channels[-4:])

    def forward(self, points: Tensor) -> Tensor:
        """``(B, n, 3)`` points -> ``(B, out_features)`` combined latent vector."""
        features = self.mlp(points)[-4:]
        return torch.cat([f.amax(dim=2) for f in reversed(features)], dim=1)


def checked_scale_indices(partial: Tensor, scale_indices: Tensor | None) -> Tensor:
    """The IFPS indices of the encoder's coarser scales (computed when ``None``), checked
    against ``partial`` and moved to its device.

    Raises:
        ValueError: ``partial`` is not ``(B, n, 3)`` with n >= 4, or the indices are not
            ``(B, n // 2)``.
    """
    check_partial(partial, min_points=2 ** (N_SCALES - 1))
    n = partial.shape[1]
    if scale_indices is None:
        scale_indices = torch.from_numpy(multi_resolution_indices(partial, N_SCALES))
    if scale_indices.shape != (partial.shape[0], n // 2):
        raise ValueError(
            f"scale_indices must have shape {(partial.shape[0], n // 2)} for partial "
            f"{tuple(partial.shape)}; got {tuple(scale_indices.shape)}"
        )
    return scale_indices.to(partial.device)


class MultiResolutionEncoder(nn.Module):
    """Multi-resolution encoder (paper §3.1): three CMLPs on IFPS scales, fused by MLP [3-1].

    Args:
        width: Multiplier of every layer's channels.
    """

    def __init__(self, width: float = 1.0) -> None:
        super().__init__()
        self.cmlps = nn.ModuleList([CMLP(width) for _ in range(N_SCALES)])
        self.fuse = nn.Sequential(nn.Conv1d(N_SCALES, 1, 1), nn.BatchNorm1d(1), nn.ReLU())
        self.out_features = self.cmlps[0].out_features

    def forward(self, partial: Tensor, scale_indices: Tensor | None = None) -> Tensor:
        """Encode partial clouds.

        Args:
            partial: ``(B, n, 3)`` partial clouds, n >= 4.
            scale_indices: Optional int64 ``(B, n // 2)`` IFPS indices into ``partial``, as
                :func:`pfnet.models.layers.multi_resolution_indices` returns (pass them to
                compute the sampling in data-loader workers); computed here when omitted.

        Returns:
            ``(B, 1920 · width)`` latent vector V.
        """
        scale_indices = checked_scale_indices(partial, scale_indices)
        n = partial.shape[1]
        latents = [self.cmlps[0](partial)]
        for s in range(1, N_SCALES):
            points = gather_points(partial, scale_indices[:, : n // 2**s])
            latents.append(self.cmlps[s](points))
        feature_map = torch.stack(latents, dim=1)  # (B, 3, 1920): the paper's map M
        return self.fuse(feature_map).squeeze(1)


def check_missing(n_missing: int) -> None:
    """Raise :class:`ConfigError` unless the decoder can predict ``n_missing`` points."""
    if n_missing < SECONDARY_POINTS or n_missing % SECONDARY_POINTS:
        raise ConfigError(
            f"the point pyramid decoder predicts M points in groups of {SECONDARY_POINTS}; "
            f"M = {n_missing} is not a positive multiple of {SECONDARY_POINTS}"
        )


class PointPyramidDecoder(nn.Module):
    """Point pyramid decoder (paper §3.2, Fig. 5).

    FC 1920→1024→512→256 (ReLU). Primary: FC 256→M1·3 centres. Secondary: FC 512→M1·128,
    ReLU, reshape (128, M1), Conv1d 128→6 — two offsets per primary centre. Detail: FC
    1024→M2·512, ReLU, reshape (512, M2), Conv1d 512→512→256 (ReLU) → 3·M/M2 offsets per
    secondary centre. No activation on coordinates.

    Args:
        in_features: Size of the latent vector V.
        n_missing: M, the number of detail points; a multiple of M2 = 128.
        width: Multiplier of every hidden layer.
    """

    def __init__(self, in_features: int, n_missing: int, width: float = 1.0) -> None:
        super().__init__()
        check_missing(n_missing)
        self.n_missing = n_missing
        fc1, fc2, fc3 = (scaled(c, width) for c in (1024, 512, 256))
        self.secondary_channels = scaled(128, width)
        self.detail_channels = scaled(512, width)
        self.fc1 = nn.Linear(in_features, fc1)
        self.fc2 = nn.Linear(fc1, fc2)
        self.fc3 = nn.Linear(fc2, fc3)
        self.primary = nn.Linear(fc3, PRIMARY_POINTS * 3)
        self.secondary_fc = nn.Linear(fc2, PRIMARY_POINTS * self.secondary_channels)
        per_primary = SECONDARY_POINTS // PRIMARY_POINTS
        self.secondary_conv = nn.Conv1d(self.secondary_channels, 3 * per_primary, 1)
        self.detail_fc = nn.Linear(fc1, SECONDARY_POINTS * self.detail_channels)
        c = self.detail_channels
        self.detail_conv = nn.Sequential(
            nn.Conv1d(c, c, 1),
            nn.ReLU(),
            nn.Conv1d(c, scaled(256, width), 1),
            nn.ReLU(),
            nn.Conv1d(scaled(256, width), 3 * (n_missing // SECONDARY_POINTS), 1),
        )
        self.relu = nn.ReLU()

    def forward(self, latent: Tensor) -> Completion:
        """``(B, in_features)`` latent -> :class:`Completion` with all three stages."""
        batch = latent.shape[0]
        x1 = self.relu(self.fc1(latent))
        x2 = self.relu(self.fc2(x1))
        x3 = self.relu(self.fc3(x2))
        primary = self.primary(x3).reshape(batch, PRIMARY_POINTS, 3)

        feat2 = self.relu(self.secondary_fc(x2)).reshape(
            batch, self.secondary_channels, PRIMARY_POINTS
        )
        offsets2 = self.secondary_conv(feat2).transpose(1, 2).reshape(batch, PRIMARY_POINTS, -1, 3)
        secondary = (primary.unsqueeze(2) + offsets2).reshape(batch, SECONDARY_POINTS, 3)

        feat3 = self.relu(self.detail_fc(x1)).reshape(batch, self.detail_channels, SECONDARY_POINTS)
        offsets3 = self.detail_conv(feat3).transpose(1, 2).reshape(batch, SECONDARY_POINTS, -1, 3)
        detail = (secondary.unsqueeze(2) + offsets3).reshape(batch, self.n_missing, 3)
        return Completion(primary, secondary, detail)


def resized_detail_head(state: dict[str, Tensor], n_missing: int) -> dict[str, Tensor]:
    """``state`` of a PF-Net-family generator, its detail head resized to ``n_missing`` points.

    Only the last layer of the detail head depends on M: it gives each of the 128 secondary
    centres ``k = M / 128`` offsets. The resized layer gives centre offset ``j`` the trained
    offset ``j mod k_trained`` (a larger M repeats them; a smaller one keeps the first), so a
    network trained at one missing ratio starts another where it was (``--init-from``). The
    repeated points split apart in training: Chamfer's nearest point is the first of equals.

    Raises:
        ConfigError: ``n_missing`` is not a positive multiple of 128.
    """
    check_missing(n_missing)
    resized = dict(state)
    prefix = "decoder.detail_conv.4."
    trained = state[prefix + "bias"].shape[0] // 3  # offsets per secondary centre
    rows = torch.tensor(
        [3 * (j % trained) + d for j in range(n_missing // SECONDARY_POINTS) for d in range(3)]
    )
    for name in ("weight", "bias"):
        resized[prefix + name] = state[prefix + name][rows].clone()
    return resized


class PFNet(CompletionModel):
    """PF-Net generator: :class:`MultiResolutionEncoder` + :class:`PointPyramidDecoder`.

    Trained with the multi-stage completion loss and the adversarial loss of a
    :class:`Discriminator` (``adversarial = True``).

    Args:
        n_points: Size N of the complete clouds the model is trained for.
        n_missing: M, the number of points it predicts (a multiple of 128).
        width: Multiplier of every hidden layer (1.0 = the paper's network).
    """

    adversarial: ClassVar[bool] = True
    multi_resolution: ClassVar[bool] = True
    multi_stage: ClassVar[bool] = True  # predicts primary and secondary centres (Eq. 2)

    def __init__(self, n_points: int, n_missing: int, width: float = 1.0) -> None:
        super().__init__()
        self.n_points = n_points
        self.n_missing = n_missing
        self.encoder = MultiResolutionEncoder(width)
        self.decoder = PointPyramidDecoder(self.encoder.out_features, n_missing, width)

    def forward(self, partial: Tensor, scale_indices: Tensor | None = None) -> Completion:
        """Predict the missing region.

        Args:
            partial: ``(B, n, 3)`` partial clouds (any n >= 4).
            scale_indices: Optional int64 ``(B, n // 2)`` IFPS indices (see
                :meth:`MultiResolutionEncoder.forward`).

        Returns:
            ``Completion(primary (B, 64, 3), secondary (B, 128, 3), detail (B, M, 3))``.
        """
        return self.decoder(self.encoder(partial, scale_indices))


class PFNetVanilla(PFNet):
    """PF-Net (vanilla): the same generator trained without the discriminator (paper Table 4)."""

    adversarial: ClassVar[bool] = False


class Discriminator(nn.Module):
    """Discriminator of predicted vs real missing regions (paper §3.3).

    Per-point MLP 3→64→64→128→256 (BN + ReLU); the last three layers are max-pooled and
    concatenated (448), then FC 448→256→128→16 (BN + ReLU) → 1. Returns logits, to be used
    with BCE-with-logits (the paper's sigmoid classifier, numerically stable).

    Args:
        width: Multiplier of every hidden layer.
    """

    def __init__(self, width: float = 1.0) -> None:
        super().__init__()
        channels = [scaled(c, width) for c in (64, 64, 128, 256)]
        self.mlp = PointMLP(channels)
        hidden = [sum(channels[1:])] + [scaled(c, width) for c in (256, 128, 16)]
        layers: list[nn.Module] = []
        for a, b in zip(hidden[:-1], hidden[1:], strict=True):
            layers += [nn.Linear(a, b), BatchNormFC(b), nn.ReLU()]
        layers.append(nn.Linear(hidden[-1], 1))
        self.head = nn.Sequential(*layers)

    def forward(self, points: Tensor) -> Tensor:
        """``(B, M, 3)`` clouds -> ``(B,)`` logits (> 0: judged real)."""
        check_partial(points)
        features = self.mlp(points)[1:]
        pooled = torch.cat([f.amax(dim=2) for f in reversed(features)], dim=1)
        return self.head(pooled).squeeze(1)
