"""PF-Net with mirror images: the partial's reflections across its own symmetry planes, given
to the encoder as extra points with flag channels (issue 34 item 3). Not the paper's network.

Furniture, airplanes, cars and ships are mirror-symmetric about a vertical plane, and a
partial scan that misses a piece on one side often still holds its mirror image on the other.
The faithful PF-Net has no way to use that: its encoder sees the partial alone. A mirror of the
input that learns nothing puts more of its points on the missing surface than PF-Net does
(docs/scan-protocol.md), so this model hands the encoder those mirror images and lets it learn
what to keep.

The planes are found inside :meth:`MirrorEncoder.forward`, from the partial alone and without
gradients, so every path that runs a generator (``complete``, ``predict``, the ONNX export)
gets them without a step of its own:

* **Search.** Vertical planes (containing the y axis, the up axis of every model frame):
  :data:`N_ANGLES` normal directions over half a turn and :data:`OFFSETS` about the partial's
  centroid. Each is scored by the share of 128 farthest-point samples of the partial whose
  reflections land in a voxel of a :data:`GRID`³ occupancy grid of the partial over the
  network's unit cube (the same score as :func:`pfnet.data.symmetry.estimate_mirror_plane`,
  with a voxel grid in place of its KD-tree so that it runs in the network).
* **Two planes**: the best, and the best whose normal is at least 30 degrees from it, as the
  mirror baseline takes (a table's other plane is often the one that fills its gap).
* **Input.** At each of the encoder's three resolutions, the scale's points with features
  ``(x, y, z, 0, 0, 0)`` and half as many mirror points (of the even-indexed points, every
  other reflected across the first plane, the rest across the second) with ``(x', y', z', 1,
  empty, share)``: ``empty`` is 1 where the reflection lands in a voxel the partial does not
  occupy (where it may fill the missing region), ``share`` is the plane's score. Each CMLP
  takes six channels and 1.5 times the points (twice cost a CPU step 2.8 times the
  vanilla's); the decoder is PF-Net's.

It trains like PF-Net (vanilla): the multi-stage Chamfer loss without the discriminator.
:meth:`PFNetMirror.grow_from` starts it from a trained PF-Net (vanilla) generator: every
weight is copied, and the first layer of each CMLP keeps its xyz weights with zeros for the
three new channels.
"""

from __future__ import annotations

import math
from typing import ClassVar

import torch
from torch import Tensor, nn

from pfnet.models.completion import Completion, CompletionModel
from pfnet.models.layers import gather_points
from pfnet.models.pfnet import CMLP as _CMLP
from pfnet.models.pfnet import (
    ENCODER_CMLP_CHANNELS,
    N_SCALES,
    PointPyramidDecoder,
    checked_scale_indices,
)

N_ANGLES = 24  # normal directions over half a turn: every 7.5 degrees
OFFSETS = tuple(0.0375 * k for k in range(-8, 9))  # about the centroid, in frame units
GRID = 32  # voxels per side of the occupancy grid over [-1, 1]^3 (0.0625 per voxel)
SEARCH_POINTS = 128  # farthest-point samples of the partial that score each plane
MAX_COS = math.cos(math.radians(30.0))  # the second plane's normal: 30 degrees away or more
IN_CHANNELS = 6  # x, y, z, mirrored, empty, share
UP_AXIS = 1


class CMLP(_CMLP):
    """PF-Net's CMLP reading ``in_channels`` features per point (:data:`IN_CHANNELS`)."""

    def __init__(self, width: float = 1.0, in_channels: int = IN_CHANNELS) -> None:
        super().__init__(width, ENCODER_CMLP_CHANNELS)
        first = self.mlp.layers[0][0]
        self.mlp.layers[0][0] = nn.Conv1d(in_channels, first.out_channels, 1)


# The ONNX export of this model must pass pfnet.inference.onnx_graph's check, which refuses
# ConstantOfShape and Range (a forged file allocated gigabytes with them): so no torch.zeros
# or arange of a size known only at run time below; the constants are buffers (not in the
# state dict) and fresh tensors are made from the input (``x * 0``).


def _occupancy(points: Tensor, empty: Tensor) -> Tensor:
    """``(B, GRID³ + 1)`` float occupancy of ``(B, n, 3)`` points (the last cell, where the
    points outside the cube go, stays 0); ``empty`` is a ``(1, GRID³ + 1)`` zero row."""
    cells = _cells(points)
    ones = (cells * 0 + 1).to(points.dtype)
    grid = torch.scatter(empty.expand(points.shape[0], -1), 1, cells, ones)
    inside = torch.ones_like(empty)
    inside[:, -1] = 0.0  # a constant: the export folds it
    return grid * inside


def _cells(points: Tensor) -> Tensor:
    """The flat voxel index of each of ``(B, ..., 3)`` points; ``GRID³`` outside the cube."""
    voxel = torch.floor((points + 1.0) * (GRID / 2.0)).long()
    inside = ((voxel >= 0) & (voxel < GRID)).all(dim=-1)
    flat = (voxel[..., 0] * GRID + voxel[..., 1]) * GRID + voxel[..., 2]
    flat = torch.where(inside, flat, GRID**3)
    return flat.reshape(points.shape[0], -1)


def _lookup(grid: Tensor, points: Tensor) -> Tensor:
    """Occupancy (0 or 1) of the voxel of each of ``(B, ..., 3)`` points, shaped ``(B, ...)``."""
    return torch.gather(grid, 1, _cells(points)).reshape(points.shape[:-1])


def _reflect(points: Tensor, normal: Tensor, offset: Tensor) -> Tensor:
    """Reflect ``(B, ..., 3)`` points across planes ``x · normal = offset``, normals
    ``(B, ..., 3)`` and offsets ``(B, ...)`` broadcasting against them."""
    distance = (points * normal).sum(dim=-1, keepdim=True) - offset.unsqueeze(-1)
    return points - 2.0 * distance * normal


def _normals() -> Tensor:
    """``(N_ANGLES, 3)`` horizontal unit normals over half a turn."""
    angles = torch.arange(N_ANGLES, dtype=torch.float64) * (math.pi / N_ANGLES)
    normals = torch.zeros(N_ANGLES, 3, dtype=torch.float64)
    horizontal = [axis for axis in range(3) if axis != UP_AXIS]
    normals[:, horizontal[0]] = torch.cos(angles)
    normals[:, horizontal[1]] = torch.sin(angles)
    return normals.float()


class MirrorPlanes(nn.Module):
    """The two vertical mirror planes of each partial cloud (no parameters, no gradients)."""

    normals: Tensor
    offsets: Tensor
    empty: Tensor

    def __init__(self) -> None:
        super().__init__()
        # constants, not weights: outside the state dict
        self.register_buffer("normals", _normals(), persistent=False)
        self.register_buffer("offsets", torch.tensor(OFFSETS), persistent=False)
        self.register_buffer("empty", torch.zeros(1, GRID**3 + 1), persistent=False)

    def forward(self, partial: Tensor, samples: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Find the planes.

        Args:
            partial: ``(B, n, 3)`` partial clouds in the network's frame.
            samples: ``(B, s, 3)`` points of each that score the candidates.

        Returns:
            ``(normals (B, 2, 3), offsets (B, 2), shares (B, 2), grid (B, GRID³ + 1))``:
            the best plane and the best at least 30 degrees from it, their scores, and the
            partial's occupancy grid.
        """
        grid = _occupancy(partial, self.empty.to(partial.dtype))
        normals = self.normals.to(partial.dtype)  # (A, 3)
        centre = partial.mean(dim=1)  # (B, 3)
        # candidate (a, d): normal a, offset centre . normal_a + d
        plane_offsets = (centre @ normals.T).unsqueeze(-1) + self.offsets.to(partial.dtype)
        reflected = _reflect(
            samples[:, None, None],  # (B, 1, 1, s, 3)
            normals[None, :, None, None],  # (1, A, 1, 1, 3)
            plane_offsets.unsqueeze(-1),  # (B, A, D, 1)
        )  # (B, A, D, s, 3)
        share = _lookup(grid, reflected).mean(dim=-1)  # (B, A, D)
        best_share, best_offset = share.max(dim=-1)  # (B, A)
        first = best_share.argmax(dim=1, keepdim=True)  # (B, 1)
        # the planes' angle from the first's: |cos| of their normals (half a turn apart is 0)
        cos = (normals[first] @ normals.T).squeeze(1).abs()  # (B, A)
        masked = torch.where(cos <= MAX_COS + 1e-4, best_share, -1.0)
        chosen = torch.cat([first, masked.argmax(dim=1, keepdim=True)], dim=1)  # (B, 2)
        offset_index = best_offset.gather(1, chosen)  # (B, 2)
        candidates = plane_offsets.gather(
            1, chosen.unsqueeze(-1).expand(-1, -1, plane_offsets.shape[2])
        )  # (B, 2, D)
        chosen_offsets = candidates.gather(2, offset_index.unsqueeze(-1)).squeeze(-1)
        return normals[chosen], chosen_offsets, best_share.gather(1, chosen), grid


class MirrorEncoder(nn.Module):
    """PF-Net's multi-resolution encoder over the partial and its mirror images.

    Args:
        width: Multiplier of every layer's channels.
        in_channels: Features per point that each CMLP reads (a subclass adds its own).
    """

    def __init__(self, width: float = 1.0, in_channels: int = IN_CHANNELS) -> None:
        super().__init__()
        self.planes = MirrorPlanes()
        self.cmlps = nn.ModuleList([CMLP(width, in_channels) for _ in range(N_SCALES)])
        self.fuse = nn.Sequential(nn.Conv1d(N_SCALES, 1, 1), nn.BatchNorm1d(1), nn.ReLU())
        self.out_features = self.cmlps[0].out_features

    def forward(self, partial: Tensor, scale_indices: Tensor | None = None) -> Tensor:
        """Encode partial clouds (the arguments of
        :meth:`pfnet.models.pfnet.MultiResolutionEncoder.forward`) -> ``(B, 1920 · width)``."""
        scale_indices = checked_scale_indices(partial, scale_indices)
        n = partial.shape[1]
        with torch.no_grad():
            # the first farthest points spread over the whole partial
            samples = gather_points(partial, scale_indices[:, : min(SEARCH_POINTS, n // 2)])
            normals, offsets, shares, grid = self.planes(partial.detach(), samples.detach())
            context = self._context(partial.detach())
        latents = []
        for s in range(N_SCALES):
            index = None if s == 0 else scale_indices[:, : n // 2**s]
            points = partial if index is None else gather_points(partial, index)
            features = self._with_mirrors(points, normals, offsets, shares, grid)
            latents.append(self.cmlps[s](self._extended(features, context, index)))
        feature_map = torch.stack(latents, dim=1)
        return self.fuse(feature_map).squeeze(1)

    def _context(self, partial: Tensor) -> Tensor | None:
        """What a subclass computes once from the whole partial for its own channels."""
        return None

    def _extended(self, features: Tensor, context: Tensor | None, index: Tensor | None) -> Tensor:
        """A subclass's channels appended to a scale's ``(B, m, 6)`` features (``index``: the
        scale's points in the partial, ``None`` for all of them)."""
        return features

    @staticmethod
    def _with_mirrors(
        points: Tensor, normals: Tensor, offsets: Tensor, shares: Tensor, grid: Tensor
    ) -> Tensor:
        """``(B, m, 3)`` points -> ``(B, m + ceil(m / 2), 6)``: the points, then the mirror
        images of the even-indexed ones (every other across the first plane, the rest across
        the second; the CMLP's max-pool does not see their order)."""
        # slices to the end written with the length: an open end is an int64 constant of
        # 2**63 - 1 in the ONNX graph, which its check refuses as a shape
        source = points[:, 0 : points.shape[1] : 2]
        half = source.shape[1]
        images, flags = [], []
        with torch.no_grad():
            for plane, part in enumerate((source[:, 0:half:2], source[:, 1:half:2])):
                image = _reflect(part, normals[:, plane : plane + 1], offsets[:, plane : plane + 1])
                empty = 1.0 - _lookup(grid, image)
                share = shares[:, plane : plane + 1].expand_as(empty)
                images.append(image)
                flags.append(torch.stack([empty * 0 + 1, empty, share], dim=2))
        original = torch.cat([points, points * 0], dim=2)
        mirrored = torch.cat([torch.cat(images, dim=1), torch.cat(flags, dim=1)], dim=2)
        return torch.cat([original, mirrored], dim=1)


class PFNetMirror(CompletionModel):
    """PF-Net (vanilla) whose encoder also reads the partial's mirror images
    (:class:`MirrorEncoder`); the decoder and the loss are PF-Net's.

    Args:
        n_points: Size N of the complete clouds the model is trained for.
        n_missing: M, the number of points it predicts (a multiple of 128).
        width: Multiplier of every hidden layer.
    """

    adversarial: ClassVar[bool] = False
    multi_resolution: ClassVar[bool] = True
    multi_stage: ClassVar[bool] = True
    # the registered models whose trained generators grow_from accepts
    grows_from: ClassVar[tuple[str, ...]] = ("pfnet", "pfnet-vanilla")

    def __init__(self, n_points: int, n_missing: int, width: float = 1.0) -> None:
        super().__init__()
        self.n_points = n_points
        self.n_missing = n_missing
        self.encoder = self._encoder(width)
        self.decoder = PointPyramidDecoder(self.encoder.out_features, n_missing, width)

    @staticmethod
    def _encoder(width: float) -> MirrorEncoder:
        return MirrorEncoder(width)

    def forward(self, partial: Tensor, scale_indices: Tensor | None = None) -> Completion:
        """Predict the missing region (the arguments and result of
        :meth:`pfnet.models.pfnet.PFNet.forward`)."""
        return self.decoder(self.encoder(partial, scale_indices))

    def grow_from(self, trained: nn.Module) -> None:
        """Start from a trained generator of :attr:`grows_from` of the same width and sizes:
        its weights, with zero weights on the channels of each CMLP's first layer that it
        does not read (the three mirror channels of a PF-Net, or a subclass's own).

        Raises:
            ValueError: A weight of another shape (another width or ``n_missing``).
        """
        source = trained.state_dict()
        own = self.state_dict()
        for key, value in source.items():
            if key not in own:
                raise ValueError(f"weight {key} of the trained generator has no place here")
            target = own[key]
            # a CMLP's first layer: the same outputs, the first of its inputs
            fewer = value.ndim == 3 and value.shape[1] < target.shape[1]
            if target.shape == value.shape:
                target.copy_(value)
            elif fewer and value.shape[::2] == target.shape[::2]:
                target.zero_()
                target[:, : value.shape[1]] = value
            else:
                raise ValueError(
                    f"weight {key} is {tuple(value.shape)} in the trained generator but "
                    f"{tuple(target.shape)} here (another width or size)"
                )
