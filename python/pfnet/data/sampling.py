"""Seeded surface sampling, point-cloud resampling and normalisation (paper §4.1).

Every shape gets its own random stream, derived from the dataset seed and the shape's stable
key (its path in the source), so a shape's points do not depend on the other shapes, on the
number of workers or on the order the workers finish in.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from pfnet.errors import DataError

__all__ = ["normalize", "resample_points", "sample_surface", "shape_rng"]


def shape_rng(seed: int, key: str) -> np.random.Generator:
    """The random generator of one shape: a function of ``(seed, key)`` only.

    Args:
        seed: The dataset seed (``--seed``), ``>= 0``.
        key: The shape's stable key, e.g. its path relative to the source.

    Returns:
        A PCG64 generator.
    """
    # surrogateescape: a file name whose bytes are not UTF-8 seeds from those bytes (issue 36)
    digest = hashlib.blake2b(key.encode("utf-8", "surrogateescape"), digest_size=16).digest()
    words = np.frombuffer(digest, dtype="<u4").tolist()
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence([seed, *words])))


def sample_surface(
    vertices: np.ndarray, faces: np.ndarray, n_points: int, rng: np.random.Generator
) -> np.ndarray:
    """Sample points uniformly on a triangle mesh's surface (area-weighted).

    Args:
        vertices: ``(V, 3)`` coordinates.
        faces: ``(F, 3)`` vertex indices of the triangles.
        n_points: Number of points to draw.
        rng: The shape's generator (:func:`shape_rng`).

    Returns:
        float64 ``(n_points, 3)``.

    Raises:
        DataError: No triangles, NaN/inf vertices, indices out of range or zero surface area.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or vertices.shape[0] == 0:
        raise DataError(f"the mesh has no vertices (shape {vertices.shape})")
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] == 0:
        raise DataError("the mesh has no triangles")
    if faces.min() < 0 or faces.max() >= vertices.shape[0]:
        raise DataError("a face refers to a vertex that does not exist")
    if not np.isfinite(vertices).all():
        raise DataError("the mesh has NaN or infinite vertex coordinates")
    corners = vertices[faces]
    edge_a = corners[:, 1] - corners[:, 0]
    edge_b = corners[:, 2] - corners[:, 0]
    area = 0.5 * np.linalg.norm(np.cross(edge_a, edge_b), axis=1)
    cumulative = np.cumsum(area)
    total = float(cumulative[-1])
    if not (np.isfinite(total) and total > 0.0):
        raise DataError("the mesh has zero surface area")
    # side="right" never picks a zero-area triangle (its cumulative area equals the previous one)
    face = np.searchsorted(cumulative, rng.random(n_points) * total, side="right")
    face = np.minimum(face, len(area) - 1)
    uv = rng.random((n_points, 2))
    outside = uv.sum(axis=1) > 1.0
    uv[outside] = 1.0 - uv[outside]
    return corners[face, 0] + uv[:, :1] * edge_a[face] + uv[:, 1:] * edge_b[face]


def resample_points(
    points: np.ndarray, n_points: int, rng: np.random.Generator, pool: int = 0
) -> np.ndarray:
    """Bring a point cloud to exactly ``n_points`` points (and a pool of more, on request).

    More points: iterative farthest point sampling (``pfnet.geometry``) from a start index
    drawn with ``rng``. Fewer points: every original point is kept, followed by copies of
    ``n_points - N`` points drawn with ``rng`` (without replacement while ``n_points <= 2N``).

    With ``pool > n_points`` the result has ``pool`` points whose first ``n_points`` are
    exactly the cloud above: IFPS is greedy, so the IFPS order of a larger sample from the
    same start begins with the smaller sample; past the cloud's own points, copies of its
    points drawn with ``rng`` fill the pool.

    Args:
        points: ``(N, 3)`` finite coordinates, ``N >= 1``.
        n_points: The wanted number of points.
        rng: The shape's generator.
        pool: Total points to return, if more than ``n_points``.

    Returns:
        float64 ``(max(n_points, pool), 3)``.
    """
    from pfnet.geometry import farthest_point_sample

    points = np.asarray(points, dtype=np.float64)
    count = points.shape[0]
    if count == 0:
        raise DataError("the point cloud is empty")
    if not np.isfinite(points).all():
        raise DataError("the point cloud has NaN or infinite coordinates")
    if count > n_points:
        start = int(rng.integers(count))
        ordered = min(count, max(n_points, pool))
        cloud = points[farthest_point_sample(points, ordered, start_index=start)]
    elif count == n_points:
        cloud = points.copy()
    else:
        extra = rng.choice(count, n_points - count, replace=n_points - count > count)
        cloud = np.concatenate([points, points[extra]])
    if pool > len(cloud):
        cloud = np.concatenate([cloud, points[rng.choice(count, pool - len(cloud))]])
    return cloud


@dataclass(frozen=True)
class Normalisation:
    """The similarity transform from a cloud's own coordinates to the unit ball.

    Attributes:
        centre: float64 ``(3,)`` subtracted first.
        radius: The largest distance of a point from ``centre``; divided next.
    """

    centre: np.ndarray
    radius: float

    def apply(self, points: np.ndarray) -> np.ndarray:
        """``(N, 3)`` input coordinates -> float32 normalised coordinates."""
        return ((np.asarray(points, np.float64) - self.centre) / self.radius).astype(np.float32)

    def invert(self, points: np.ndarray) -> np.ndarray:
        """``(M, 3)`` normalised coordinates -> float32 input coordinates."""
        return (np.asarray(points, np.float64) * self.radius + self.centre).astype(np.float32)


def fixed_size(points: np.ndarray, n: int) -> np.ndarray:
    """float32 ``(n, 3)``: a cloud reduced by iterative farthest point sampling from point 0,
    or repeated cyclically when smaller (point ``k`` is point ``k mod N``): the deterministic
    resampling of a network's input, the heading reader's and the nearest-crop look-up's."""
    from pfnet.geometry import farthest_point_sample

    cloud = np.ascontiguousarray(points, dtype=np.float32)
    if len(cloud) > n:
        index = farthest_point_sample(cloud, n, start_index=0)
    else:
        index = np.arange(n) % len(cloud)
    return np.ascontiguousarray(cloud[index], dtype=np.float32)


def unit_ball(points: np.ndarray) -> Normalisation | None:
    """The authors' ``pc_normalize`` as a transform: centre at the centroid (the mean of the
    points), divide by the largest distance to it; ``None`` when all points coincide."""
    points = np.asarray(points, dtype=np.float64)
    centre = points.mean(axis=0)
    radius = float(np.sqrt(((points - centre) ** 2).sum(axis=1)).max())
    if not (np.isfinite(radius) and radius > 0.0):
        return None
    return Normalisation(centre=centre, radius=radius)


def normalize(points: np.ndarray, n_reference: int | None = None) -> np.ndarray:
    """Centre a cloud at the origin and scale it into the unit ball, as the authors do
    (:func:`unit_ball`), so every coordinate lies in ``[-1, 1]``.

    Args:
        points: ``(N, 3)``.
        n_reference: Take the centroid and radius of the first ``n_reference`` points only
            and apply them to all (a pool of extra points follows the data set's cloud; its
            points may lie slightly outside the unit ball).

    Returns:
        float32 ``(N, 3)``; its first ``n_reference`` points have mean 0 and largest norm 1.

    Raises:
        DataError: All points coincide (nothing to scale).
    """
    points = np.asarray(points, dtype=np.float64)
    transform = unit_ball(points[:n_reference] if n_reference else points)
    if transform is None:
        raise DataError("the shape is degenerate: all sampled points coincide")
    return transform.apply(points)
