"""Scanner partials: what a depth camera sees of a shape (issue 34, item 4).

The paper's crop removes the points nearest a viewpoint; a depth camera instead sees the
surface facing it and misses everything behind it. :func:`visible_mask` splits a cloud into
the points a camera sees and the hidden ones with a z-buffer: every point is projected
through a pinhole at the camera, looking at the centre of the cloud's bounding sphere, onto
an image whose pixel holds about two points of a surface facing the camera (1.5 times the
surface's point spacing); a point is seen when it lies within a depth tolerance of the
nearest point of its own pixel (2 pixel widths: a surface's own slope across a pixel) and of
the nearest of its 3 × 3 neighbourhood (4 widths: the splat, which closes the holes a sampled
front surface leaves where a pixel caught none of its points, while a slanted surface keeps
its far side of the window). Katz et al.'s hidden point removal (spherical flip and convex
hull) would need scipy's convex hull, and scipy is only in the ``bench`` extra; the z-buffer
is a few numpy passes over the points (about a millisecond for 2,048), cheap enough to run
in the data loader, with no new Rust kernel to keep.

A scanner *sample* has the sizes the models take: the model predicts
``M = round(missing_ratio · N)`` points, so the partial is the visible points resampled to
``N − M`` and the missing region ``M`` of the hidden ones, spread over the hidden surface by
farthest point sampling. On SweetHome3D's furniture a camera 2–3 radii away sees 42 % of a
shape's 2,048 points (docs/scanner.md), so a missing ratio of 0.5, the nearest of the
paper's ratios, keeps both parts' densities close to the complete cloud's.

Cameras (:func:`scanner_camera`) stand on a sphere of 2–3 radii around the shape, mostly
above the horizon (elevations from −15° to 60°), as a person or a robot scans furniture.
Training draws one per ``(seed, epoch, index)``; the test protocol gives sample ``i`` the
camera drawn from ``(seed, i)`` (:func:`scanner_test_cameras`), as
:func:`pfnet.data.crops.test_protocol_crop` gives it ``VIEWPOINTS[i % 5]``.

Both scan the sample's ``N``-point cloud (with ``fresh_points``, a new draw from the pool),
not the whole pool: the z-buffer's resolution follows the density, and a denser cloud lets
it see thin parts as one-sided (on SweetHome3D, a third of 8,192 points is seen against 42 %
of 2,048), so training and test partials are scanned at the same density.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pfnet.data.crops import missing_count
from pfnet.errors import ConfigError, DataError

__all__ = [
    "CAMERA_DISTANCES",
    "CAMERA_ELEVATIONS",
    "CameraImage",
    "camera_image",
    "scanner_camera",
    "scanner_crop",
    "scanner_sample",
    "scanner_test_cameras",
    "scanner_test_crop",
    "test_sample_rng",
    "visible_mask",
]

CAMERA_DISTANCES = (2.0, 3.0)
"""Camera distances from the shape's centre, in radii of the unit ball (uniform)."""

CAMERA_ELEVATIONS = (-15.0, 60.0)
"""Camera elevations above the horizon, in degrees (uniform in the sine, so uniform on the
sphere's band): about four cameras in five look down on the shape."""

PIXEL_SPACINGS = 1.5
"""A pixel's width at the camera's distance, in the surface's point spacings."""

SPLAT = 1
"""Pixels a point's depth spreads to on each side (a 3 × 3 splat)."""

PIXEL_TOLERANCE = 2.0
"""A point is seen within this many pixel widths (at its depth) behind its pixel's nearest."""

SPLAT_TOLERANCE = 4.0
"""... and within this many behind the nearest of its splat's neighbourhood. Measured on a
forged sphere and two parallel planes (tests/test_crops_scanner.py): no back point seen, the
whole near plane seen, the sphere's cap seen up to where its surface turns 60° from the
camera."""

MIN_SHARE = 0.25
"""A scanner sample needs at least this share of its ``N − M`` partial points (and of its
``M`` missing points) distinct: below it the sample would be mostly copies."""

MAX_CAMERAS = 16
"""Cameras :func:`scanner_sample` tries before it gives up on a cloud."""

_MAX_PIXELS = 1024  # image width cap (8 MB of depths): furniture needs tens to a few hundred
_SPACING_QUERIES = 512  # points whose nearest neighbour estimates the surface's spacing
_TEST_STREAM = 0x5CA9  # keeps the test cameras apart from the scan poses' streams


@dataclass(frozen=True)
class CameraImage:
    """The projection of a cloud into a camera's z-buffer (see :func:`camera_image`).

    Attributes:
        rows: int64 ``(P,)`` pixel row of each point.
        cols: int64 ``(P,)`` pixel column.
        depth: float64 ``(P,)`` distance from the camera.
        pixel: float64 ``(P,)`` a pixel's width at the point's depth (the tolerances' unit).
        width: Pixels on each side of the square image.
    """

    rows: np.ndarray
    cols: np.ndarray
    depth: np.ndarray
    pixel: np.ndarray
    width: int


def _surface_spacing(points: np.ndarray) -> float:
    """``sqrt(area / P)``: the side of the square of surface each point stands for.

    Estimated from the mean nearest-neighbour distance of up to 512 evenly chosen points to
    the others; for points spread uniformly (a Poisson process of density ρ on a surface)
    that mean is ``1 / (2 sqrt(ρ))``. Points that coincide with another one (copies) are
    left out of the mean.
    """
    from pfnet.geometry import nearest_neighbors

    n = len(points)
    chosen = np.zeros(n, bool)
    chosen[np.linspace(0, n - 1, min(_SPACING_QUERIES, n // 2)).astype(np.int64)] = True
    sq, _ = nearest_neighbors(points[chosen].astype(np.float32), points[~chosen].astype(np.float32))
    distances = np.sqrt(sq[sq > 0].astype(np.float64))
    if len(distances) == 0:
        return 0.0
    # the others are a share (n - q) / n of the cloud: their spacing is that much wider
    return 2.0 * float(np.mean(distances)) * math.sqrt((n - chosen.sum()) / n)


def camera_image(points: np.ndarray, camera: np.ndarray, *, what: str = "the cloud"):
    """Project ``points`` into the z-buffer of a pinhole camera at ``camera``.

    The camera looks at the centre of the cloud's bounding sphere (its centroid and largest
    distance from it); its image is the square that holds that sphere, split into pixels
    whose width at the camera's distance is :data:`PIXEL_SPACINGS` point spacings of the
    surface (``sqrt(area / P)``, :func:`_surface_spacing`), so that a front surface puts a
    point in nearly every pixel and the splat closes the rest.

    Args:
        points: ``(P, 3)`` cloud.
        camera: ``(3,)`` position, outside the bounding sphere.
        what: The cloud's name in error messages (e.g. ``"sample 3 (chair-12)"``).

    Returns:
        A :class:`CameraImage`.

    Raises:
        DataError: The camera is inside the bounding sphere, or the cloud has too few
            distinct points to have a surface.
    """
    points = np.asarray(points, np.float64)
    camera = np.asarray(camera, np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 4:
        raise DataError(f"{what}: points must have shape (P, 3) with P >= 4, got {points.shape}")
    if not np.isfinite(points).all():
        raise DataError(f"{what}: the points must be finite (NaN or inf found)")
    if camera.shape != (3,) or not np.all(np.isfinite(camera)):
        raise DataError(f"{what}: camera must be 3 finite coordinates, got {camera!r}")
    centre = points.mean(axis=0)
    radius = float(np.sqrt(((points - centre) ** 2).sum(axis=1).max()))
    distance = float(np.linalg.norm(camera - centre))
    if distance <= radius * 1.001:
        raise DataError(
            f"{what}: the camera at {np.round(camera, 3).tolist()} is {distance:.3g} from the "
            f"cloud's centre, inside its bounding sphere (radius {radius:.3g}); a scanner "
            "camera must stand outside the shape"
        )
    spacing = _surface_spacing(points)
    if spacing <= 0:
        raise DataError(f"{what}: the cloud's points all coincide; it has no surface to see")
    forward = (centre - camera) / distance
    helper = np.eye(3)[int(np.argmin(np.abs(forward)))]
    right = np.cross(forward, helper)
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    relative = points - camera
    ahead = relative @ forward  # > 0: the bounding sphere lies in front of the camera
    half = radius / math.sqrt(distance**2 - radius**2)  # tan of the sphere's half-angle
    pitch = PIXEL_SPACINGS * spacing / distance  # a pixel's width in tangent units
    width = int(min(_MAX_PIXELS, max(8, math.ceil(2.0 * half / pitch))))
    pitch = 2.0 * half / width
    cols = np.clip(((relative @ right / ahead + half) / pitch).astype(np.int64), 0, width - 1)
    rows = np.clip(((relative @ up / ahead + half) / pitch).astype(np.int64), 0, width - 1)
    depth = np.sqrt((relative**2).sum(axis=1))
    return CameraImage(rows, cols, depth, pitch * depth, width)


def visible_mask(points: np.ndarray, camera: np.ndarray, *, what: str = "the cloud") -> np.ndarray:
    """Which points of a cloud a depth camera at ``camera`` sees (a z-buffer, module doc).

    Args:
        points: ``(P, 3)`` cloud (a shape's surface points; denser is finer).
        camera: ``(3,)`` position outside the cloud's bounding sphere.
        what: The cloud's name in error messages.

    Returns:
        bool ``(P,)``: ``True`` where the point is seen.

    Raises:
        DataError: As :func:`camera_image`.
    """
    image = camera_image(points, camera, what=what)
    width = image.width
    nearest = np.full(width * width, np.inf)
    np.minimum.at(nearest, image.rows * width + image.cols, image.depth)
    nearest = nearest.reshape(width, width)
    padded = np.pad(nearest, SPLAT, constant_values=np.inf)
    splat = nearest.copy()
    for dr in range(2 * SPLAT + 1):
        for dc in range(2 * SPLAT + 1):
            np.minimum(splat, padded[dr : dr + width, dc : dc + width], out=splat)
    own = nearest[image.rows, image.cols] + PIXEL_TOLERANCE * image.pixel
    return (image.depth <= own) & (
        image.depth <= splat[image.rows, image.cols] + SPLAT_TOLERANCE * image.pixel
    )


def _check_up_axis(up_axis: int) -> None:
    if up_axis not in (0, 1, 2):
        raise ConfigError(f"up_axis must be 0, 1 or 2, got {up_axis!r}")


def scanner_camera(rng: np.random.Generator, *, up_axis: int = 1) -> np.ndarray:
    """One random camera position, float64 ``(3,)``, around a shape in the unit ball.

    A uniform heading, an elevation in :data:`CAMERA_ELEVATIONS` (uniform on the sphere's
    band) and a distance in :data:`CAMERA_DISTANCES`, with ``up_axis`` the data set's up
    (y for SweetHome3D and the other prepared sources).
    """
    _check_up_axis(up_axis)
    heading = rng.uniform(0.0, 2.0 * np.pi)
    low, high = (math.sin(math.radians(e)) for e in CAMERA_ELEVATIONS)
    height = rng.uniform(low, high)
    distance = rng.uniform(*CAMERA_DISTANCES)
    across = math.sqrt(1.0 - height**2)
    a, b = (axis for axis in range(3) if axis != up_axis)
    camera = np.zeros(3)
    camera[a], camera[b] = across * math.cos(heading), across * math.sin(heading)
    camera[up_axis] = height
    return camera * distance


def test_sample_rng(index: int, seed: int = 0) -> np.random.Generator:
    """The generator of test sample ``index``: its camera is the first draw, then the
    resampling (and, when needed, further cameras)."""
    return np.random.default_rng([seed, index, _TEST_STREAM])


def scanner_test_cameras(n_samples: int, *, seed: int = 0, up_axis: int = 1) -> np.ndarray:
    """The test protocol's cameras, float64 ``(n_samples, 3)``: sample ``i``'s is the first
    draw of :func:`test_sample_rng` ``(i, seed)`` alone, so it does not depend on the split's
    size (a camera that sees or hides too little is followed by the generator's next draws,
    see :func:`scanner_sample`)."""
    _check_up_axis(up_axis)
    cameras = [scanner_camera(test_sample_rng(i, seed), up_axis=up_axis) for i in range(n_samples)]
    return np.array(cameras, np.float64).reshape(n_samples, 3)


def _resample(n_have: int, n_want: int, rng: np.random.Generator) -> np.ndarray:
    """``n_want`` indices into ``n_have`` items: without repeats while there are enough,
    else every item once and the rest drawn again."""
    if n_have >= n_want:
        return np.sort(rng.choice(n_have, n_want, replace=False))
    return np.sort(np.concatenate([np.arange(n_have), rng.choice(n_have, n_want - n_have)]))


def _shortfall(n_visible: int, n_hidden: int, n_points: int, n_missing: int) -> str | None:
    """Why a view cannot make a sample (it sees or hides too few points), or ``None``."""
    for name, have, want in (
        ("sees", n_visible, n_points - n_missing),
        ("hides", n_hidden, n_missing),
    ):
        least = max(1, math.ceil(MIN_SHARE * want))
        if have < least:
            return (
                f"{name} only {have} of its {n_visible + n_hidden} points; a scanner sample of "
                f"{n_points} points with {n_missing} missing needs at least {least}"
            )
    return None


def _sample(visible, hidden, n_points, n_missing, rng):
    """The visible points resampled to ``N − M`` and ``M`` hidden ones spread by FPS."""
    from pfnet.geometry import farthest_point_sample

    partial = visible[_resample(len(visible), n_points - n_missing, rng)]
    start = int(rng.integers(len(hidden)))
    spread = np.sort(farthest_point_sample(hidden, min(n_missing, len(hidden)), start))
    if len(spread) < n_missing:  # fewer hidden than the model predicts: some twice
        spread = np.sort(np.concatenate([spread, rng.choice(spread, n_missing - len(spread))]))
    return partial, hidden[spread]


def scanner_crop(
    points: np.ndarray,
    camera: np.ndarray,
    n_points: int,
    n_missing: int,
    rng: np.random.Generator,
    *,
    what: str = "the cloud",
) -> tuple[np.ndarray, np.ndarray]:
    """A fixed-size scanner sample of one cloud seen from ``camera``: ``(partial, missing)``.

    The partial is the points the camera sees (:func:`visible_mask`), resampled to
    ``n_points − n_missing`` (at random, without repeats while there are enough); the missing
    region is ``n_missing`` of the hidden points by farthest point sampling from a random
    start (repeats only when fewer are hidden).

    Args:
        points: ``(P, 3)`` complete cloud.
        camera: ``(3,)`` camera position, outside the cloud's bounding sphere.
        n_points: ``N``, points of a complete sample.
        n_missing: ``M``, points the model predicts.
        rng: The sample's generator (the resampling and the FPS start).
        what: The cloud's name in error messages.

    Returns:
        float32 ``(N − M, 3)`` and ``(M, 3)``.

    Raises:
        DataError: The camera is inside the cloud, or it sees fewer than :data:`MIN_SHARE`
            of ``N − M`` points or hides fewer than that share of ``M``.
    """
    points = np.asarray(points, np.float32)
    seen = visible_mask(points, camera, what=what)
    reason = _shortfall(int(seen.sum()), int((~seen).sum()), n_points, n_missing)
    if reason is not None:
        where = np.round(np.asarray(camera, np.float64), 3).tolist()
        raise DataError(f"{what}: the camera at {where} {reason}")
    return _sample(points[seen], points[~seen], n_points, n_missing, rng)


def scanner_sample(
    points: np.ndarray,
    n_points: int,
    n_missing: int,
    rng: np.random.Generator,
    *,
    up_axis: int = 1,
    what: str = "the cloud",
    best_effort: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """A scanner sample from a random camera (:func:`scanner_camera`, drawn from ``rng``).

    A camera that sees or hides too few points (a table top seen from above hides almost
    nothing of a single-sided mesh) is replaced by the next draw, as a person scanning would
    step aside, up to :data:`MAX_CAMERAS`; about one draw in fifty on SweetHome3D's
    furniture at a missing ratio of 0.5.

    Args:
        best_effort: When no camera makes a sample (a banknote, a rug: one flat sheet), take
            the one nearest to making it, its points repeated, if it sees and hides at least
            one point; training crops do, so that one such shape does not stop a run. The
            test protocol does not.

    Raises:
        DataError: No camera of :data:`MAX_CAMERAS` makes a sample (the message names the
            cloud with ``what`` and says what the last one saw).
    """
    points = np.asarray(points, np.float32)
    best, best_share = None, 0.0
    for _ in range(MAX_CAMERAS):
        camera = scanner_camera(rng, up_axis=up_axis)
        seen = visible_mask(points, camera, what=what)
        n_seen, n_hidden = int(seen.sum()), int((~seen).sum())
        reason = _shortfall(n_seen, n_hidden, n_points, n_missing)
        if reason is None:
            return _sample(points[seen], points[~seen], n_points, n_missing, rng)
        share = min(n_seen / (n_points - n_missing), n_hidden / n_missing)
        if share > best_share:
            best, best_share = seen, share
    if best_effort and best is not None:
        return _sample(points[best], points[~best], n_points, n_missing, rng)
    raise DataError(
        f"{what}: none of {MAX_CAMERAS} scanner cameras makes a sample; the last {reason} "
        "(a flat or single-sided shape? choose another missing ratio or crop)"
    )


def scanner_test_crop(
    points: np.ndarray, missing_ratio: float, *, seed: int = 0, up_axis: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Crop a split with the scanner test protocol: sample ``i`` is scanned from
    ``scanner_test_cameras(S)[i]``, resampled by the rest of :func:`test_sample_rng`
    ``(i, seed)`` (:func:`scanner_sample`).

    Args:
        points: ``(S, N, 3)`` complete clouds, in dataset order (the unit ball).
        missing_ratio: ``r``: the model predicts ``M = round(r·N)`` points (0.5 fits the
            hidden share of furniture best).
        seed: Seed of the cameras and the resampling.
        up_axis: The data set's up axis.

    Returns:
        ``(partial, missing)``: float32 ``(S, N − M, 3)`` and ``(S, M, 3)``.
    """
    points = np.asarray(points)
    if points.ndim != 3 or points.shape[2] != 3:
        raise ConfigError(f"points must have shape (S, N, 3), got {points.shape}")
    n_samples, n_points = points.shape[:2]
    m = missing_count(n_points, missing_ratio)
    _check_up_axis(up_axis)
    pairs = [
        scanner_sample(
            points[i], n_points, m, test_sample_rng(i, seed), up_axis=up_axis, what=f"sample {i}"
        )
        for i in range(n_samples)
    ]
    partial = np.array([p for p, _ in pairs], np.float32).reshape(n_samples, n_points - m, 3)
    missing = np.array([q for _, q in pairs], np.float32).reshape(n_samples, m, 3)
    return partial, missing


# Not tests: keep pytest from collecting these where a test module imports them by name.
scanner_test_cameras.__test__ = False  # type: ignore[attr-defined]
scanner_test_crop.__test__ = False  # type: ignore[attr-defined]
test_sample_rng.__test__ = False  # type: ignore[attr-defined]
