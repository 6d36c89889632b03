"""The baselines of the paper's ablation (Table 4): MLP, CMLP and MR-CMLP.

Each encodes the partial cloud and predicts the M missing points with two fully connected
layers [1024, M·3] ("each layer followed by BN and ReLU", paper §4.4; the output layer has
neither, as it emits coordinates). PF-Net (vanilla) is :class:`pfnet.models.PFNetVanilla`.
"""

from __future__ import annotations

from typing import ClassVar

from torch import Tensor, nn

from pfnet.models.completion import Completion, CompletionModel
from pfnet.models.layers import PointMLP, check_partial, fc_block, scaled
from pfnet.models.pfnet import BASELINE_CMLP_CHANNELS, CMLP, MultiResolutionEncoder


class _FCDecoder(nn.Module):
    """FC in→1024 (BN + ReLU) → M·3: the baselines' decoder."""

    def __init__(self, in_features: int, n_missing: int, width: float) -> None:
        super().__init__()
        if n_missing < 1:
            raise ValueError(f"n_missing must be positive; got {n_missing}")
        self.n_missing = n_missing
        hidden = scaled(1024, width)
        self.layers = nn.Sequential(fc_block(in_features, hidden), nn.Linear(hidden, n_missing * 3))

    def forward(self, latent: Tensor) -> Tensor:
        """``(B, in_features)`` -> ``(B, M, 3)``."""
        return self.layers(latent).reshape(latent.shape[0], self.n_missing, 3)


class PointNetEncoder(nn.Module):
    """PointNet-MLP encoder (paper Fig. 4a): per-point MLP [64-128-256-512-1024], max-pool.

    Args:
        width: Multiplier of every layer's channels.
    """

    def __init__(self, width: float = 1.0) -> None:
        super().__init__()
        channels = [scaled(c, width) for c in (64, 128, 256, 512, 1024)]
        self.mlp = PointMLP(channels)
        self.out_features = channels[-1]

    def forward(self, points: Tensor) -> Tensor:
        """``(B, n, 3)`` -> ``(B, out_features)``."""
        return self.mlp(points)[-1].amax(dim=2)


class _Baseline(CompletionModel):
    """An encoder followed by the two-layer FC decoder; no discriminator."""

    adversarial: ClassVar[bool] = False
    multi_resolution: ClassVar[bool] = False
    multi_stage: ClassVar[bool] = False

    def __init__(self, encoder: nn.Module, n_points: int, n_missing: int, width: float) -> None:
        super().__init__()
        self.n_points = n_points
        self.n_missing = n_missing
        self.encoder = encoder
        self.decoder = _FCDecoder(encoder.out_features, n_missing, width)

    def forward(self, partial: Tensor, scale_indices: Tensor | None = None) -> Completion:
        """Predict the missing region.

        Args:
            partial: ``(B, n, 3)`` partial clouds.
            scale_indices: IFPS indices for multi-resolution encoders (see
                :meth:`pfnet.models.MultiResolutionEncoder.forward`); ignored otherwise.

        Returns:
            ``Completion(None, None, detail (B, M, 3))``.
        """
        check_partial(partial)
        if self.multi_resolution:
            latent = self.encoder(partial, scale_indices)
        else:
            latent = self.encoder(partial)
        return Completion(None, None, self.decoder(latent))


class MLPCompletion(_Baseline):
    """Single-resolution MLP baseline: PointNet-MLP encoder + FC [1024, M·3].

    Args:
        n_points: Size N of the complete clouds the model is trained for.
        n_missing: M, the number of points it predicts.
        width: Multiplier of every hidden layer.
    """

    def __init__(self, n_points: int, n_missing: int, width: float = 1.0) -> None:
        super().__init__(PointNetEncoder(width), n_points, n_missing, width)


class CMLPCompletion(_Baseline):
    """Single-resolution CMLP baseline: CMLP encoder (1920-d) + FC [1024, M·3].

    The encoder has the paper's five layers [64-128-256-512-1024], as the authors' baseline
    (``CMLP_autoencoder``); PF-Net's and MR-CMLP's encoders have six (an extra 64 layer).

    Args:
        n_points: Size N of the complete clouds the model is trained for.
        n_missing: M, the number of points it predicts.
        width: Multiplier of every hidden layer.
    """

    def __init__(self, n_points: int, n_missing: int, width: float = 1.0) -> None:
        super().__init__(CMLP(width, BASELINE_CMLP_CHANNELS), n_points, n_missing, width)


class MRCMLPCompletion(_Baseline):
    """Multi-resolution CMLP baseline: PF-Net's encoder + FC [1024, M·3].

    Args:
        n_points: Size N of the complete clouds the model is trained for.
        n_missing: M, the number of points it predicts.
        width: Multiplier of every hidden layer.
    """

    multi_resolution: ClassVar[bool] = True

    def __init__(self, n_points: int, n_missing: int, width: float = 1.0) -> None:
        super().__init__(MultiResolutionEncoder(width), n_points, n_missing, width)
