"""Hostile input to the Rust core: huge counts and coordinates give a clear ValueError (never a
panic, an abort or a silent ``inf``), and duplicate points give exact answers."""

from __future__ import annotations

import time

import numpy as np
import pytest
from brute import far_from_tilted, nearest_naive

from pfnet import _core
from pfnet.geometry import (
    MAX_COORDINATE,
    MAX_REGIONS,
    chamfer,
    crop_multi_region,
    farthest_point_sample,
    nearest_neighbors,
    random_crop,
)


def _cloud(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1, 1, size=(n, 3)).astype(np.float32)


@pytest.mark.parametrize("n_regions", [MAX_REGIONS + 1, 10**9, 2**40, 2**61])
def test_huge_region_counts_are_refused_before_any_allocation(n_regions: int) -> None:
    with pytest.raises(ValueError, match=rf"n_regions must be in 1\.\.{MAX_REGIONS}"):
        random_crop(_cloud(16), 4, seed=0, n_regions=n_regions, directions="sphere")
    # the core checks too, for callers that skip pfnet.geometry
    with pytest.raises(ValueError, match="n_regions must be in"):
        _core.random_centres(0, 2, n_regions, "sphere")


def test_the_largest_region_count_works() -> None:
    partial, missing = random_crop(
        _cloud(64), 8, seed=1, n_regions=MAX_REGIONS, directions="sphere"
    )
    assert partial.shape == (56, 3) and missing.shape == (8, 3)


def test_multi_region_crops_are_bounded_in_regions_and_time() -> None:
    # O(K·N): 65,536 regions on 65,537 points once took 36 s, 50,000 viewpoints 25 s
    cloud = _cloud(65_537)
    views = np.random.default_rng(1).normal(size=(MAX_REGIONS + 1, 3))
    with pytest.raises(ValueError, match=r"viewpoints holds 257 regions, more than the 256"):
        crop_multi_region(cloud, views, 50_000)
    start = time.perf_counter()
    partial, missing = random_crop(
        cloud, 65_536, seed=3, n_regions=MAX_REGIONS, directions="sphere"
    )
    assert missing.shape == (65_536, 3) and partial.shape == (1, 3)
    crop_multi_region(cloud, views[:MAX_REGIONS], 50_000)
    assert time.perf_counter() - start < 10  # about 0.6 s


@pytest.mark.parametrize("scale", [1e19, 1e20, 1e30, 3e38])
def test_coordinates_whose_squares_overflow_are_refused_by_every_kernel(scale: float) -> None:
    huge = (_cloud(32) * np.float32(scale)).astype(np.float32)
    assert np.isfinite(huge).all() and np.abs(huge).max() > MAX_COORDINATE
    small = _cloud(32, 1)
    for call in (
        lambda: farthest_point_sample(huge, 4),
        lambda: nearest_neighbors(huge, small),
        lambda: nearest_neighbors(small, huge),
        lambda: chamfer(small, huge),
        lambda: random_crop(huge, 4, seed=0),
    ):
        with pytest.raises(ValueError, match=r"beyond ±1e18.*scale the cloud down"):
            call()


def test_large_but_accepted_coordinates_give_the_scaled_answers() -> None:
    points = _cloud(256)
    scaled = points * np.float32(1e17)
    assert np.array_equal(farthest_point_sample(scaled, 16), farthest_point_sample(points, 16))
    d_small, i_small = nearest_neighbors(points[:50], points[50:])
    d_large, i_large = nearest_neighbors(scaled[:50], scaled[50:])
    assert np.isfinite(d_large).all()
    assert np.array_equal(i_small, i_large)
    np.testing.assert_allclose(d_large, d_small * 1e34, rtol=1e-5)


def test_duplicate_points_give_exact_distances_and_first_indices() -> None:
    rng = np.random.default_rng(2)
    centres = _cloud(20, 3)
    clustered = centres[rng.integers(0, 20, size=20_000)]  # 1,000 copies of each on average
    identical = np.repeat(centres[:1], 20_000, axis=0)
    query = _cloud(500, 4)
    for reference in (clustered, identical):
        distances, index = nearest_neighbors(query, reference)
        brute = ((query[:, None, :] - reference[None, :, :]) ** 2).sum(-1)
        np.testing.assert_allclose(distances, brute.min(axis=1), rtol=1e-6, atol=1e-7)
        # every index names the first copy of its point
        first = {tuple(p): i for i, p in reversed(list(enumerate(reference.tolist())))}
        assert all(first[tuple(reference[i].tolist())] == i for i in index)
    assert chamfer(identical, identical) == (0.0, 0.0)


def _degenerate_layouts(n: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """(query, reference) pairs on which kiddo's tree went quadratic (issue 14): at 100k points
    1.4 s (collinear), 2.0 s (far queries), 10 s (tiny) and 19 s (subnormal) on 2 cores."""
    rng = np.random.default_rng(14)
    uniform = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    line = np.zeros((n, 3), np.float32)
    line[:, 0] = np.arange(n) / n
    planar = uniform.copy()
    planar[:, 2] = 0.25
    tiny = (rng.random((n, 3)) * 1e-25).astype(np.float32)  # float32 squares underflow to 0
    subnormal = (rng.random((n, 3)) * 1e-40).astype(np.float32)
    subnormal[n // 2] = 1e17
    # Oblique lines and planes and far tiny clusters, on which cells alone pruned too little and
    # a query visited O(n) leaves (audit 9, G2).
    t = rng.random(n)
    diagonal = np.c_[t, t, t].astype(np.float32)
    a, b = rng.random(n), rng.random(n)
    oblique_plane = np.c_[a, b, 1 - a - b].astype(np.float32)
    cube = rng.random((n, 3)).astype(np.float32)
    blob = rng.random((n, 3)) * 1e-6
    far_clusters = (blob + (np.arange(n) % 2)[:, None]).astype(np.float32)
    apart = (blob + 1e6 * (np.arange(n) % 2)[:, None]).astype(np.float32)
    return {
        "oblique line, noisy queries": (
            (diagonal + rng.normal(0, 0.01, (n, 3))).astype(np.float32),
            diagonal,
        ),
        "oblique line, queries in a cube": (cube, diagonal),
        "oblique plane, queries in a cube": (cube, oblique_plane),
        "tilted plane, queries in a cube": (
            cube,
            np.c_[a, b, 0.3 * a + 0.7 * b].astype(np.float32),
        ),
        "far tiny clusters, queries in a cube": (cube, far_clusters),
        "tiny clusters 1e6 apart, queries between": ((cube * 1e6).astype(np.float32), apart),
        "collinear": (line, line),
        "planar": (planar, planar),
        "far queries": (uniform + np.float32(100), uniform),
        "tiny": (tiny, tiny),
        "tiny, other queries": ((rng.random((n, 3)) * 1e-25).astype(np.float32), tiny),
        "subnormal cluster and a huge point": (subnormal, subnormal),
        # Queries far from a tilted plane or line, where every point near a query's foot ties
        # with the nearest in float32 (audit K1: 100k points at H = 1e3 took 21 s).
        "tilted plane, queries 1 to 1e5 away": far_from_tilted("plane", n, [1.0, 1e3, -1e5, 1e5]),
        "tilted line, queries 1 to 1e5 away": far_from_tilted("line", n, [1.0, 1e3, -1e5, 1e5]),
    }


@pytest.mark.parametrize("layout", list(_degenerate_layouts(8)))
def test_degenerate_layouts_give_the_brute_force_answers(layout: str) -> None:
    query, reference = _degenerate_layouts(3000)[layout]
    distances, index = nearest_neighbors(query, reference)
    expected = nearest_naive(query, reference)
    np.testing.assert_array_equal(distances, expected[0])
    np.testing.assert_array_equal(index, expected[1])


@pytest.mark.parametrize("layout", list(_degenerate_layouts(8)))
def test_degenerate_layouts_at_100k_points(layout: str) -> None:
    # Seconds each before issue 14, milliseconds now; checked exactly on a sample of queries.
    query, reference = _degenerate_layouts(100_000)[layout]
    distances, index = nearest_neighbors(query, reference)
    # the distance is the float64 one of the point named, rounded to float32
    diff = query.astype(np.float64) - reference[index]
    np.testing.assert_array_equal(
        distances,
        (diff[:, 0] * diff[:, 0] + diff[:, 1] * diff[:, 1] + diff[:, 2] * diff[:, 2]).astype(
            np.float32
        ),
    )
    sample = np.random.default_rng(1).choice(len(query), 96, replace=False)
    expected = nearest_naive(query[sample], reference)
    np.testing.assert_array_equal(distances[sample], expected[0])
    np.testing.assert_array_equal(index[sample], expected[1])


def test_chamfer_of_degenerate_clouds_with_themselves_is_zero() -> None:
    # 8.7 s (collinear, 300k) and over 120 s (tiny, 200k) before issue 14.
    line = np.zeros((300_000, 3), np.float32)
    line[:, 0] = np.arange(300_000) / 300_000
    tiny = (np.random.default_rng(3).random((200_000, 3)) * 1e-25).astype(np.float32)
    assert chamfer(line, line) == (0.0, 0.0)
    assert chamfer(tiny, tiny) == (0.0, 0.0)


@pytest.mark.parametrize("value", [np.nan, np.inf, 1e19, 1e300])
@pytest.mark.parametrize("size", [{"radius": 0.5}, {"n_missing": 4}])
def test_both_crop_sizes_check_every_coordinate(value: float, size: dict) -> None:
    from pfnet.geometry import VIEWPOINTS, crop_by_viewpoint

    points = _cloud(32).astype(np.float64)
    points[7, 1] = value
    with pytest.raises(ValueError, match="points (contains NaN|has a coordinate beyond)"):
        crop_by_viewpoint(points, VIEWPOINTS[0], **size)
