"""Evaluation protocols: how the input of each test sample is made and how it is scored.

A protocol names everything a published number depends on: where the partial input comes
from (a crop of the complete cloud, or the benchmark's own partial scan), what the model's
output is compared with, and which metrics, in which units. ``pfnet predict --protocol`` and
``pfnet evaluate --protocol`` take these names.

* ``pfnet`` — PF-Net's own (DESIGN.md §3, §5): test sample *i* loses the ``round(r·N)``
  points nearest ``VIEWPOINTS[i % 5]``; the prediction is the missing region, scored with
  Eq. 1's two squared terms ×1000 (region ``missing``, or ``whole`` with the partial input).
* ``pcn`` — the PCN benchmark as PoinTr, SnowflakeNet and SeedFormer score it: the
  benchmark's partial scan (view ``00.pcd`` of each test shape) is the input, the output is
  the whole completion, compared with the 16,384-point complete cloud; CD-L1 ×1000 is the
  headline number.
* ``shapenet55`` — ShapeNet-55 and ShapeNet-34 (PoinTr, ``tools/runner.py`` ``test``): each
  normalised 8,192-point test cloud is cropped from each of 8 fixed viewpoints
  :data:`SHAPENET_VIEWPOINTS`: the ``int(8192·r)`` points nearest the viewpoint go
  (``r`` = 0.25 / 0.5 / 0.75, *easy* / *median* / *hard*), the rest, in order of increasing
  distance, are reduced to 2,048 points by farthest point sampling from their first point;
  the whole completion is compared with the 8,192 points. CD-L2 ×1000 is the headline number.
* ``kitti`` — the KITTI cars of the PCN release (PoinTr, ``KITTI_metric.py``): no ground
  truth; each car's LiDAR points, pose-normalised from its box
  (:func:`pfnet.data.kitti.object_pose`, PoinTr's ``NormalizeObjectPose``), are the input;
  the whole completion, in that normalised frame, is scored by Fidelity (input →
  completion) and MMD (completion → nearest reference car by CD-L2), both ×1000.

Metrics of ``pcn`` and ``shapenet55`` are PoinTr's (``utils/metrics.py``,
``extensions/chamfer_dist/__init__.py``): see :func:`pfnet.evaluation.metrics.sample_metrics`. As
PoinTr's ``ChamferDistanceL1/L2(ignore_zeros=True)`` at batch size 1, points whose
coordinates sum to exactly 0 are left out of both clouds before the Chamfer terms (not
before the F-score).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from pfnet.errors import ConfigError, DataError

__all__ = [
    "PROTOCOLS",
    "PROTOCOL_NAMES",
    "SHAPENET_INPUT_POINTS",
    "SHAPENET_VIEWPOINTS",
    "Protocol",
    "check_protocol_data",
    "get_protocol",
    "shapenet_crop",
    "shapenet_missing_count",
]

SHAPENET_VIEWPOINTS = np.array(
    [
        [1, 1, 1],
        [1, 1, -1],
        [1, -1, 1],
        [-1, 1, 1],
        [-1, -1, 1],
        [-1, 1, -1],
        [1, -1, -1],
        [-1, -1, -1],
    ],
    dtype=np.float32,
)
"""PoinTr's 8 test viewpoints, in its order (``tools/runner.py``, ``choice``); used as
points, not normalised."""

SHAPENET_POINTS = 8192
"""Points of each ShapeNet-55/34 cloud (PoinTr's ``shapenet_pc/*.npy``)."""

SHAPENET_INPUT_POINTS = 2048
"""Points of the ShapeNet-55/34 input after the crop (PoinTr: ``misc.fps(partial, 2048)``)."""


@dataclass(frozen=True)
class Protocol:
    """A named evaluation protocol.

    Attributes:
        name: The name ``--protocol`` takes.
        title: One line for tables and reports.
        input: ``"crop"`` (the partial input is cut from the complete cloud) or ``"given"``
            (the benchmark's partial scan, stored by ``pfnet prepare``).
        prediction: What a prediction file holds: ``"missing"`` (the missing region) or
            ``"complete"`` (the whole completion).
        views: Test inputs made from each shape (8 for ShapeNet-55/34, else 1).
        ratios: The missing ratios the benchmark defines (empty: not a crop).
        default_ratio: The ratio used when none is given.
        scaled: Metrics reported ×1000.
        headline: The metric papers compare first.
        ignore_zeros: Leave points whose coordinates sum to 0 out of the Chamfer terms
            (PoinTr's ``ignore_zeros=True``).
        source: Where the protocol is defined.
    """

    name: str
    title: str
    input: str
    prediction: str
    views: int
    ratios: tuple[float, ...]
    default_ratio: float | None
    scaled: tuple[str, ...]
    headline: str
    ignore_zeros: bool
    source: str

    @property
    def suffixes(self) -> list[str]:
        """What follows a shape's name in the stem of each of its prediction files."""
        return [""] if self.views == 1 else [f"_view{v}" for v in range(self.views)]

    def sample_keys(self, category: str, name: str) -> list[str]:
        """The ``<category>/<file stem>`` of each prediction file of one shape."""
        return [f"{category}/{name}{suffix}" for suffix in self.suffixes]


_POINTR_METRICS = ("pred_to_gt", "gt_to_pred", "cd_l2", "cd_l1")

PROTOCOLS: dict[str, Protocol] = {
    "pfnet": Protocol(
        name="pfnet",
        title="PF-Net: crop from VIEWPOINTS[i % 5], missing region scored, squared CD ×1000",
        input="crop",
        prediction="missing",
        views=1,
        ratios=(0.25, 0.5, 0.75),
        default_ratio=0.25,
        scaled=("pred_to_gt", "gt_to_pred", "cd_l2"),
        headline="cd_l2",
        ignore_zeros=False,
        source="PF-Net (CVPR 2020) §4; DESIGN.md §3, §5",
    ),
    "pcn": Protocol(
        name="pcn",
        title="PCN: given partial scan, whole completion vs 16,384 points, CD-L1 ×1000",
        input="given",
        prediction="complete",
        views=1,
        ratios=(),
        default_ratio=None,
        scaled=_POINTR_METRICS,
        headline="cd_l1",
        ignore_zeros=True,
        source="PoinTr datasets/PCNDataset.py, tools/runner.py test(), utils/metrics.py",
    ),
    "shapenet55": Protocol(
        name="shapenet55",
        title="ShapeNet-55/34: 8 viewpoints, 2,048-point input, whole completion vs 8,192 "
        "points, CD-L2 ×1000",
        input="crop",
        prediction="complete",
        views=len(SHAPENET_VIEWPOINTS),
        ratios=(0.25, 0.5, 0.75),
        default_ratio=0.25,
        scaled=_POINTR_METRICS,
        headline="cd_l2",
        ignore_zeros=True,
        source="PoinTr tools/runner.py test(), utils/misc.py seprate_point_cloud, utils/metrics.py",
    ),
    "kitti": Protocol(
        name="kitti",
        title="KITTI cars: pose-normalised LiDAR car, whole completion, Fidelity and MMD ×1000",
        input="given",
        prediction="complete",
        views=1,
        ratios=(),
        default_ratio=None,
        scaled=("fidelity", "mmd"),
        headline="mmd",
        ignore_zeros=True,
        source="PoinTr datasets/KITTIDataset.py, datasets/data_transforms.py "
        "NormalizeObjectPose, KITTI_metric.py",
    ),
}
"""The protocols by name."""

_ALIASES = {"shapenet34": "shapenet55", "shapenet-55": "shapenet55", "shapenet-34": "shapenet55"}

PROTOCOL_NAMES = (*PROTOCOLS, *_ALIASES)
"""Every name :func:`get_protocol` accepts (the protocols' and their other names)."""


def get_protocol(name: str) -> Protocol:
    """The protocol called ``name`` (``shapenet34`` is ``shapenet55``'s other name).

    Raises:
        ConfigError: No protocol has that name.
    """
    key = _ALIASES.get(str(name).lower(), str(name).lower())
    if key not in PROTOCOLS:
        raise ConfigError(f"protocol must be one of {', '.join(PROTOCOL_NAMES)}, got {name!r}")
    return PROTOCOLS[key]


def shapenet_missing_count(n_points: int, ratio: float) -> int:
    """Points the ShapeNet-55/34 crop removes: ``int(n_points · ratio)`` (PoinTr truncates).

    Raises:
        ConfigError: The ratio is not in (0, 1), or removes no point or every point.
    """
    if not (isinstance(ratio, (int, float)) and 0.0 < ratio < 1.0):
        raise ConfigError(f"missing ratio must be in (0, 1), got {ratio!r}")
    removed = int(n_points * ratio)
    if not 1 <= removed < n_points:
        raise ConfigError(f"missing ratio {ratio} removes {removed} of {n_points} points")
    return removed


def shapenet_crop(points: np.ndarray, ratio: float, view: int) -> np.ndarray:
    """PoinTr's ShapeNet-55/34 test input for one viewpoint.

    The ``int(N·r)`` points nearest ``SHAPENET_VIEWPOINTS[view]`` are removed; the rest, in
    order of increasing distance to it (PoinTr's ``argsort``; ties here in index order), are
    reduced to :data:`SHAPENET_INPUT_POINTS` by farthest point sampling from the first one
    (the nearest kept point; ``furthest_point_sample`` starts at index 0).

    Args:
        points: ``(N, 3)`` or ``(B, N, 3)`` complete clouds.
        ratio: Share of the points removed (0.25, 0.5, 0.75 in the benchmark).
        view: Index into :data:`SHAPENET_VIEWPOINTS`.

    Returns:
        float32 ``(2048, 3)`` or ``(B, 2048, 3)``; fewer than 2,048 kept points are returned
        as they are (sorted by distance).

    Raises:
        ConfigError: A ratio or view out of range, or a view that is not an integer.
        DataError: Points that are not finite ``(N, 3)`` or ``(B, N, 3)`` clouds.
    """
    from pfnet.geometry import farthest_point_sample

    views = len(SHAPENET_VIEWPOINTS)
    if isinstance(view, bool) or not isinstance(view, (int, np.integer)) or not 0 <= view < views:
        raise ConfigError(f"view must be an integer in [0, {views}), got {view!r}")
    clouds = np.asarray(points, dtype=np.float32)
    if clouds.ndim not in (2, 3) or clouds.shape[-1] != 3:
        raise DataError(f"points must have shape (N, 3) or (B, N, 3), got {clouds.shape}")
    if not np.isfinite(clouds).all():
        raise DataError("points must be finite: some coordinates are NaN or infinite")
    single = clouds.ndim == 2
    if single:
        clouds = clouds[None]
    removed = shapenet_missing_count(clouds.shape[1], ratio)
    centre = SHAPENET_VIEWPOINTS[view]
    distance = np.sqrt(((clouds - centre) ** 2).sum(axis=2, dtype=np.float32))
    order = np.argsort(distance, axis=1, kind="stable")[:, removed:]
    kept = np.take_along_axis(clouds, order[:, :, None], axis=1)
    if kept.shape[1] >= SHAPENET_INPUT_POINTS:  # PoinTr samples 2,048 of 2,048 too (reorders)
        index = farthest_point_sample(kept, SHAPENET_INPUT_POINTS, start_index=0)
        kept = np.take_along_axis(kept, index[:, :, None], axis=1)
    kept = np.ascontiguousarray(kept, dtype=np.float32)
    return kept[0] if single else kept


def check_protocol_data(protocol: Protocol, data_dir: str | os.PathLike[str]) -> None:
    """Refuse a data set that a benchmark protocol does not define.

    A benchmark's number means something only on that benchmark's data: ``pcn`` on a data set
    prepared from PCN, ``shapenet55`` on one prepared from ShapeNet-55/34 (8,192 points a
    cloud), ``kitti`` on KITTI's cars. ``pfnet`` crops any data set.

    Raises:
        DataError: The manifest records another benchmark, or none, or (``shapenet55``) clouds
            of another size.
    """
    from pfnet.data.format import read_manifest

    if protocol.name == "pfnet":
        return
    manifest = read_manifest(data_dir)
    benchmark = manifest.get("benchmark")
    made = benchmark.get("protocol") if isinstance(benchmark, dict) else None
    source = manifest.get("source")
    kind = source.get("format") if isinstance(source, dict) else None
    points = manifest.get("points")
    shown = f"{made or kind or 'pfnet'} data set"
    if isinstance(points, int) and not isinstance(points, bool):
        shown += f" of {points:,} points a cloud"
    if made != protocol.name:
        raise DataError(
            f"the {protocol.name} protocol needs a data set prepared from its benchmark, "
            f"but {data_dir} is a {shown}"
        )
    if protocol.name == "shapenet55" and points != SHAPENET_POINTS:
        raise DataError(
            f"the shapenet55 protocol needs clouds of {SHAPENET_POINTS:,} points, "
            f"but {data_dir} is a {shown}"
        )
