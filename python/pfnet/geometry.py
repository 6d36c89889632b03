"""Exact point cloud geometry for PF-Net, computed by pfnet's Rust core.

Every function accepts float32 or float64 arrays of any memory layout (integer arrays are
converted to float64), shaped ``(N, 3)`` for one cloud or ``(B, N, 3)`` for a batch, and
releases the GIL while it computes; batches run in parallel across cores. Bad input raises
:class:`pfnet.errors.GeometryError`, a ``ValueError`` (shapes, sizes, NaN/inf), or ``TypeError``
(dtypes), naming the argument. A cloud may hold at most ``MAX_POINTS`` (2**32 - 1) points.

Precision: sampling and nearest neighbours work on float32 coordinates (float64 input is
rounded to float32 first); Chamfer terms are accumulated in float64; crops rank distances in
float64 and return the input's own points in the input's dtype.
"""

from __future__ import annotations

import numbers
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pfnet import _core
from pfnet.errors import GeometryError

__all__ = [
    "VIEWPOINTS",
    "chamfer",
    "crop_by_viewpoint",
    "crop_multi_region",
    "farthest_point_sample",
    "nearest_neighbors",
    "random_crop",
]

VIEWPOINTS: NDArray[np.float32] = _core.VIEWPOINTS.astype(np.float32)
"""The authors' five crop centres, float32 ``(5, 3)``:
``(1,0,0), (0,0,1), (1,0,1), (-1,0,0), (-1,1,0)``."""
VIEWPOINTS.flags.writeable = False

MAX_REGIONS: int = _core.MAX_REGIONS
"""The most regions :func:`random_crop` and :func:`crop_multi_region` may remove at once (256).

The paper crops one region and the command line at most five; each region costs a pass over
the points (256 regions on 65,536 points take about 0.3 s; 65,536 regions took 36 s)."""
MAX_COORDINATE: float = _core.MAX_COORDINATE
"""The largest coordinate magnitude the kernels accept (squared distances stay finite)."""
MAX_POINTS: int = _core.MAX_POINTS
"""The most points one cloud may hold, 2**32 - 1: the core stores point indices as 32 bits."""


def _as_cloud(
    name: str, value: ArrayLike, dtypes: tuple[type, ...] = (np.float32,)
) -> tuple[np.ndarray, bool]:
    """Validate a cloud argument; return it as a C-contiguous (B, N, 3) array and whether it
    was batched. The dtype is kept if it is in ``dtypes``, else converted to ``dtypes[0]``
    (float input) or float64 (other numeric input, then narrowed to ``dtypes[0]``)."""
    array = np.asarray(value)
    if array.dtype.kind not in "fiub" or array.dtype.kind == "b":
        raise TypeError(f"{name} must be a float32 or float64 array, got dtype {array.dtype}")
    if array.ndim not in (2, 3) or array.shape[-1] != 3:
        raise GeometryError(f"{name} must have shape (N, 3) or (B, N, 3), got {array.shape}")
    if array.shape[-2] == 0:
        raise GeometryError(
            f"{name} is empty: shape {array.shape}, a cloud needs at least one point"
        )
    if array.shape[-2] > MAX_POINTS:
        # Checked before the conversions below, which could copy the whole array first.
        raise GeometryError(
            f"{name} has {array.shape[-2]} points per cloud (shape {array.shape}), more than the "
            f"{MAX_POINTS} (2^32 - 1) that one cloud may hold: point indices are 32-bit"
        )
    batched = array.ndim == 3
    if array.dtype.type not in dtypes:
        # float64 beyond float32's range becomes inf, which the core refuses by name: numpy's
        # own warning about it would only come first
        with np.errstate(over="ignore"):
            array = array.astype(dtypes[0] if array.dtype.kind == "f" else np.float64)
            if array.dtype.type not in dtypes:
                array = array.astype(dtypes[0])
    array = np.ascontiguousarray(array)
    return (array if batched else array[None]), batched


def _check_pair(a: str, x: np.ndarray, xb: bool, b: str, y: np.ndarray, yb: bool, shapes) -> None:
    if xb != yb or x.shape[0] != y.shape[0]:
        raise GeometryError(
            f"{a} and {b} must both be single clouds or batches of the same size, "
            f"got shapes {shapes[0]} and {shapes[1]}"
        )


def _count(name: str, value: object) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an integer, got {type(value).__name__} {value!r}")
    return int(value)


def farthest_point_sample(
    points: ArrayLike, n_samples: int, start_index: int = 0
) -> NDArray[np.int64]:
    """Iterative farthest point sampling (IFPS), exact.

    The first index is ``start_index``; each next one is the point whose squared distance to
    the chosen set is largest, ties going to the lowest index. The result equals the naive
    O(N·K) float32 algorithm from the same start; a KD-tree that caches the largest distance
    per node (QuickFPS) makes it fast. PF-Net uses IFPS for its input scales (§3.1) and for
    the primary/secondary ground truth of the multi-stage loss (§3.3).

    Args:
        points: ``(N, 3)`` or ``(B, N, 3)`` coordinates (computed in float32).
        n_samples: How many indices to pick, ``1 <= n_samples <= N``.
        start_index: The first index, ``0 <= start_index < N``.

    Returns:
        int64 indices ``(n_samples,)``, or ``(B, n_samples)`` for a batch.
    """
    shape = np.shape(points)
    cloud, batched = _as_cloud("points", points)
    n_samples = _count("n_samples", n_samples)
    start_index = _count("start_index", start_index)
    n = cloud.shape[1]
    if not 1 <= n_samples <= n:
        raise GeometryError(
            f"n_samples must be in 1..{n} for points of shape {shape}, got {n_samples}"
        )
    if not 0 <= start_index < n:
        raise GeometryError(
            f"start_index must be in 0..{n - 1} for points of shape {shape}, got {start_index}"
        )
    indices = _core.farthest_point_sample(cloud, n_samples, start_index)
    return indices if batched else indices[0]


def nearest_neighbors(
    query: ArrayLike, reference: ArrayLike
) -> tuple[NDArray[np.float32], NDArray[np.int64]]:
    """Exact nearest neighbour in ``reference`` of every ``query`` point (KD-tree).

    The nearest point has the smallest squared distance computed in float64 from the float32
    coordinates, the lowest index among equal ones; that distance is returned rounded to float32.

    Args:
        query: ``(Q, 3)`` or ``(B, Q, 3)``.
        reference: ``(R, 3)`` or ``(B, R, 3)``, batched like ``query``.

    Returns:
        ``(sq_dist, index)``: float32 squared Euclidean distances and int64 indices into
        ``reference``, each ``(Q,)`` or ``(B, Q)``.
    """
    shapes = (np.shape(query), np.shape(reference))
    q, qb = _as_cloud("query", query)
    r, rb = _as_cloud("reference", reference)
    _check_pair("query", q, qb, "reference", r, rb, shapes)
    sq_dist, index = _core.nearest_neighbors(q, r)
    return (sq_dist, index) if qb else (sq_dist[0], index[0])


def chamfer(pred: ArrayLike, gt: ArrayLike):
    """The two directed Chamfer terms of PF-Net's Eq. (1), with a KD-tree, accumulated in float64.

    ``pred_to_gt`` is the mean over predicted points of the squared distance to the nearest
    ground-truth point (the paper's "Pred → GT" error); ``gt_to_pred`` the reverse ("GT → Pred").
    The paper's tables report both ×1000.

    Args:
        pred: ``(P, 3)`` or ``(B, P, 3)``.
        gt: ``(G, 3)`` or ``(B, G, 3)``, batched like ``pred``; ``G`` may differ from ``P``.

    Returns:
        ``(pred_to_gt, gt_to_pred)``: two floats, or two float64 ``(B,)`` arrays for a batch.
    """
    shapes = (np.shape(pred), np.shape(gt))
    p, pb = _as_cloud("pred", pred)
    g, gb = _as_cloud("gt", gt)
    _check_pair("pred", p, pb, "gt", g, gb, shapes)
    pred_to_gt, gt_to_pred = _core.chamfer(p, g)
    if pb:
        return pred_to_gt, gt_to_pred
    return float(pred_to_gt[0]), float(gt_to_pred[0])


_CROP_DTYPES = (np.float32, np.float64)


def _core_crop(kind: str, dtype: np.dtype):
    suffix = "f32" if dtype == np.float32 else "f64"
    return getattr(_core, f"crop_{kind}_{suffix}")


def _viewpoints(name: str, value: ArrayLike, batch: int, batched: bool, ndim: int) -> np.ndarray:
    """Validate viewpoint(s): a single one is broadcast over the batch."""
    try:
        array = np.asarray(value, dtype=np.float64)
    except OverflowError:  # a Python int such as 10**400
        raise GeometryError(f"{name} must be finite, got a number beyond float64") from None
    single = array.ndim == ndim - 1
    expected = "(3,) or (B, 3)" if ndim == 2 else "(K, 3) or (B, K, 3)"
    if array.ndim not in (ndim - 1, ndim) or array.shape[-1] != 3 or (not batched and not single):
        if not batched:
            expected = "(3,)" if ndim == 2 else "(K, 3)"
        raise GeometryError(f"{name} must have shape {expected}, got {array.shape}")
    if not np.isfinite(array).all():
        raise GeometryError(f"{name} must be finite, got {array.tolist()}")
    if single:
        array = np.broadcast_to(array, (batch, *array.shape))
    elif array.shape[0] != batch:
        raise GeometryError(f"{name} has {array.shape[0]} rows for a batch of {batch} clouds")
    return np.ascontiguousarray(array)


def _check_missing(n_missing: object, n: int, shape: tuple) -> int:
    n_missing = _count("n_missing", n_missing)
    if not 0 <= n_missing < n:
        raise GeometryError(
            f"n_missing must be in 0..{n - 1} (fewer than the {n} points of points with shape "
            f"{shape}), got {n_missing}"
        )
    return n_missing


def crop_by_viewpoint(
    points: ArrayLike,
    viewpoint: ArrayLike,
    n_missing: int | None = None,
    radius: float | None = None,
):
    """Split a cloud into the partial input and the missing region seen from a viewpoint.

    PF-Net's training and test crops (§4.1): the points nearest a viewpoint are removed. Give
    exactly one of ``n_missing`` (remove that many nearest points, ties: lowest index first) or
    ``radius`` (remove every point within that distance).

    Args:
        points: ``(N, 3)`` or ``(B, N, 3)``.
        viewpoint: ``(3,)``, or ``(B, 3)`` for one per cloud of a batch (see ``VIEWPOINTS``).
        n_missing: Points to remove, ``0 <= n_missing < N``.
        radius: Removal radius (Euclidean), ``>= 0``.

    Returns:
        ``(partial, missing)`` in the input dtype, each keeping the input's point order:
        ``(N - n_missing, 3)`` and ``(n_missing, 3)`` (``(B, ...)`` for a batch). With ``radius``
        the sizes vary, so a batch returns two lists of ``(n_i, 3)`` arrays.
    """
    if (n_missing is None) == (radius is None):
        raise GeometryError("give exactly one of n_missing or radius")
    shape = np.shape(points)
    cloud, batched = _as_cloud("points", points, _CROP_DTYPES)
    views = _viewpoints("viewpoint", viewpoint, cloud.shape[0], batched, 2)
    if radius is not None:
        if isinstance(radius, (str, bytes, bool)) or not isinstance(radius, numbers.Real):
            raise TypeError(f"radius must be a real number, got {type(radius).__name__}")
        try:
            radius = float(radius)
        except OverflowError:  # a Python int or Fraction such as 10**400
            raise GeometryError(
                "radius must be a finite number >= 0, got one beyond float64"
            ) from None
        if not (np.isfinite(radius) and radius >= 0):
            raise GeometryError(f"radius must be a finite number >= 0, got {radius}")
        crop = _core_crop("radius", cloud.dtype)
        parts = [crop(c, v, radius) for c, v in zip(cloud, views)]
        if not batched:
            return parts[0]
        return [p for p, _ in parts], [m for _, m in parts]
    n_missing = _check_missing(n_missing, cloud.shape[1], shape)
    partial, missing = _core_crop("count", cloud.dtype)(cloud, views, n_missing)
    return (partial, missing) if batched else (partial[0], missing[0])


def crop_multi_region(points: ArrayLike, viewpoints: ArrayLike, n_missing: int):
    """Remove ``n_missing`` points split among several viewpoints.

    Region ``k`` removes, of the points still present, those nearest ``viewpoints[k]``; the
    per-region counts differ by at most one (earlier regions take the remainder).

    Args:
        points: ``(N, 3)`` or ``(B, N, 3)``.
        viewpoints: ``(K, 3)``, or ``(B, K, 3)`` for a batch; ``1 <= K <=``
            :data:`MAX_REGIONS`.
        n_missing: Total points to remove, ``0 <= n_missing < N``.

    Returns:
        ``(partial, missing)`` as in :func:`crop_by_viewpoint` (missing points in input order).
    """
    shape = np.shape(points)
    cloud, batched = _as_cloud("points", points, _CROP_DTYPES)
    views = _viewpoints("viewpoints", viewpoints, cloud.shape[0], batched, 3)
    if views.shape[1] == 0:
        raise GeometryError("viewpoints is empty: give at least one viewpoint")
    n_missing = _check_missing(n_missing, cloud.shape[1], shape)
    partial, missing = _core_crop("multi", cloud.dtype)(cloud, views, n_missing)
    return (partial, missing) if batched else (partial[0], missing[0])


def random_crop(
    points: ArrayLike,
    n_missing: int,
    *,
    seed: int,
    n_regions: int = 1,
    directions: Literal["viewpoints", "sphere"] = "viewpoints",
):
    """Seeded random crop for training.

    The authors pick one of the five ``VIEWPOINTS`` at random per sample; ``n_regions > 1``
    removes the points around several distinct centres (as :func:`crop_multi_region`), and
    ``directions="sphere"`` draws centres uniformly on the unit sphere instead. The same seed
    gives the same crops on every platform; each cloud of a batch gets its own centres.

    Args:
        points: ``(N, 3)`` or ``(B, N, 3)``.
        n_missing: Total points to remove, ``0 <= n_missing < N``.
        seed: Non-negative integer seed.
        n_regions: Number of removed regions (at most 5 with ``"viewpoints"``, else at most
            :data:`MAX_REGIONS`).
        directions: ``"viewpoints"`` or ``"sphere"``.

    Returns:
        ``(partial, missing)`` as in :func:`crop_by_viewpoint`.
    """
    seed = _count("seed", seed)
    n_regions = _count("n_regions", n_regions)
    if not 0 <= seed < 2**64:  # reduced mod 2**64, 2**64 would be seed 0 again
        raise GeometryError(f"seed must be an integer in [0, 2**64), got {seed}")
    if directions not in ("viewpoints", "sphere"):
        raise GeometryError(f"directions must be 'viewpoints' or 'sphere', got {directions!r}")
    limit = 5 if directions == "viewpoints" else MAX_REGIONS
    if not 1 <= n_regions <= limit:
        raise GeometryError(
            f"n_regions must be in 1..{limit} for directions={directions!r}, got {n_regions}"
        )
    batched = np.ndim(points) == 3
    batch = np.shape(points)[0] if batched else 1
    centres = _core.random_centres(seed, batch, n_regions, directions)
    return crop_multi_region(points, centres if batched else centres[0], n_missing)
