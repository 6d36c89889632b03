"""pfnet.geometry against naive numpy references: random, degenerate and adversarial clouds."""

import numpy as np
import pytest
from brute import far_from_tilted, nearest_naive
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from pfnet import geometry as g
from pfnet.errors import GeometryError

# ---------------------------------------------------------------- naive references


def fps_naive(points: np.ndarray, k: int, start: int = 0) -> np.ndarray:
    """The naive O(N·K) float32 IFPS: dx*dx + dy*dy + dz*dz, ties to the lowest index."""
    p = np.asarray(points, dtype=np.float32)
    min_dist = np.full(len(p), np.inf, dtype=np.float32)
    chosen = [start]
    for _ in range(k - 1):
        s = p[chosen[-1]]
        d = (p[:, 0] - s[0]) ** 2 + (p[:, 1] - s[1]) ** 2 + (p[:, 2] - s[2]) ** 2
        min_dist = np.minimum(min_dist, d)
        chosen.append(int(np.argmax(min_dist)))
    return np.array(chosen, dtype=np.int64)


def assert_nearest_naive(query, reference, sq_dist, index):
    want_sq_dist, want_index = nearest_naive(query, reference)
    np.testing.assert_array_equal(sq_dist, want_sq_dist)
    np.testing.assert_array_equal(index, want_index)


def chamfer_naive(pred, gt):
    return float(nearest_naive(pred, gt)[0].astype(np.float64).mean()), float(
        nearest_naive(gt, pred)[0].astype(np.float64).mean()
    )


def crop_naive(points, viewpoint, n_missing):
    p = np.asarray(points)
    d = ((p.astype(np.float64) - np.asarray(viewpoint, dtype=np.float64)) ** 2).sum(axis=1)
    order = np.lexsort((np.arange(len(p)), d))  # by distance, then index
    mask = np.zeros(len(p), dtype=bool)
    mask[order[:n_missing]] = True
    return p[~mask], p[mask]


def cloud(n, seed=0, dtype=np.float32):
    return np.random.default_rng(seed).uniform(-1, 1, (n, 3)).astype(dtype)


def degenerate_clouds():
    rng = np.random.default_rng(5)
    grid = np.stack(np.meshgrid(*[np.arange(6)] * 3, indexing="ij"), -1).reshape(-1, 3)
    planar = rng.uniform(-1, 1, (700, 3))
    planar[:, 2] = 0.25
    t = rng.uniform(-1, 1, (600, 1))
    collinear = t * np.array([[1.0, 2.0, -0.5]])
    duplicated = np.repeat(rng.uniform(-1, 1, (50, 3)), 13, axis=0)
    return {
        "grid with ties": np.concatenate([grid, grid]).astype(np.float32),
        "planar": planar.astype(np.float32),
        "collinear": collinear.astype(np.float32),
        "duplicated": duplicated.astype(np.float32),
        "all equal": np.full((900, 3), 0.3, dtype=np.float32),
        "single point": np.zeros((1, 3), dtype=np.float32),
    }


# ---------------------------------------------------------------- farthest point sampling


def test_fps_hand_computed():
    points = np.array([[0, 0, 0], [1, 0, 0], [5, 0, 0], [2, 0, 0]], dtype=np.float32)
    np.testing.assert_array_equal(g.farthest_point_sample(points, 3), [0, 2, 3])
    batch = np.stack([points, points[::-1]])
    np.testing.assert_array_equal(g.farthest_point_sample(batch, 2), [[0, 2], [0, 1]])


@pytest.mark.parametrize(("n", "k"), [(10, 10), (300, 64), (2048, 512), (6000, 300)])
@pytest.mark.parametrize("start", [0, 7])
def test_fps_matches_naive_on_random_clouds(n, k, start):
    p = cloud(n, seed=n + start)
    np.testing.assert_array_equal(g.farthest_point_sample(p, k, start), fps_naive(p, k, start))


@pytest.mark.parametrize("name", list(degenerate_clouds()))
def test_fps_matches_naive_on_degenerate_clouds(name):
    p = degenerate_clouds()[name]
    k = min(len(p), 100)
    np.testing.assert_array_equal(g.farthest_point_sample(p, k), fps_naive(p, k))


def test_fps_all_equal_repeats_index_zero_like_the_naive_algorithm():
    p = np.ones((5, 3), dtype=np.float32)
    np.testing.assert_array_equal(g.farthest_point_sample(p, 3, start_index=2), [2, 0, 0])


def test_fps_batch_equals_each_cloud_and_float64_and_views():
    batch = np.stack([cloud(1500, s) for s in range(5)])
    got = g.farthest_point_sample(batch, 100, start_index=3)
    assert got.shape == (5, 100) and got.dtype == np.int64
    for b in range(5):
        np.testing.assert_array_equal(got[b], fps_naive(batch[b], 100, 3))
    np.testing.assert_array_equal(g.farthest_point_sample(batch.astype(np.float64), 100, 3), got)
    # Non-contiguous: every other point of a Fortran-ordered copy.
    view = np.asfortranarray(cloud(3000, 9))[::2]
    np.testing.assert_array_equal(g.farthest_point_sample(view, 50), fps_naive(view, 50))
    one = g.farthest_point_sample(batch[:1], 10)
    assert one.shape == (1, 10)


@settings(max_examples=40, deadline=None)
@given(
    hnp.arrays(
        np.float32,
        st.tuples(st.integers(1, 200), st.just(3)),
        elements=st.sampled_from([-1.0, -0.5, 0.0, 0.25, 1.0, 3.0]) | st.floats(-2, 2, width=32),
    ),
    st.data(),
)
def test_fps_property_matches_naive(points, data):
    k = data.draw(st.integers(1, len(points)))
    start = data.draw(st.integers(0, len(points) - 1))
    got = g.farthest_point_sample(points, k, start)
    np.testing.assert_array_equal(got, fps_naive(points, k, start))
    assert got[0] == start


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        (
            {"points": np.zeros((0, 3)), "n_samples": 1},
            ValueError,
            r"points is empty: shape \(0, 3\)",
        ),
        (
            {"points": np.zeros((5, 2)), "n_samples": 1},
            ValueError,
            r"\(N, 3\) or \(B, N, 3\), got \(5, 2\)",
        ),
        ({"points": np.zeros(3), "n_samples": 1}, ValueError, r"got \(3,\)"),
        (
            {"points": np.zeros((5, 3)), "n_samples": 6},
            ValueError,
            r"n_samples must be in 1\.\.5 .* got 6",
        ),
        ({"points": np.zeros((5, 3)), "n_samples": 0}, ValueError, r"n_samples must be in 1\.\.5"),
        (
            {"points": np.zeros((5, 3)), "n_samples": 2, "start_index": 5},
            ValueError,
            r"start_index must be in 0\.\.4",
        ),
        (
            {"points": np.zeros((5, 3)), "n_samples": 2, "start_index": -1},
            ValueError,
            r"start_index",
        ),
        (
            {"points": np.zeros((5, 3)), "n_samples": 2.5},
            TypeError,
            r"n_samples must be an integer",
        ),
        (
            {"points": np.array([["a", "b", "c"]]), "n_samples": 1},
            TypeError,
            r"points must be a float32 or float64 array, got dtype <U1",
        ),
    ],
)
def test_fps_errors(kwargs, error, match):
    with pytest.raises(error, match=match) as raised:
        g.farthest_point_sample(**kwargs)
    # bad values raise pfnet's own ValueError subclass; bad types stay TypeError
    assert isinstance(raised.value, GeometryError) == (error is ValueError)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_points_are_named_with_their_position(bad):
    p = cloud(20)
    p[13, 1] = bad
    with pytest.raises(
        ValueError,
        match=r"points contains NaN or infinite coordinates \(first at batch 0, point 13\)",
    ):
        g.farthest_point_sample(p, 3)
    batch = np.stack([cloud(20), p])
    with pytest.raises(ValueError, match=r"batch 1, point 13"):
        g.farthest_point_sample(batch, 3)
    with pytest.raises(ValueError, match=r"gt contains NaN"):
        g.chamfer(cloud(5), p)
    with pytest.raises(ValueError, match=r"query contains NaN"):
        g.nearest_neighbors(p, cloud(5))
    with pytest.raises(ValueError, match=r"points contains NaN"):
        g.crop_by_viewpoint(p, g.VIEWPOINTS[0], n_missing=2)


# ---------------------------------------------------------------- nearest neighbours and chamfer


@pytest.mark.parametrize(("nq", "nr"), [(1, 1), (1, 500), (700, 3), (5000, 6000)])
def test_nearest_neighbors_matches_brute_force(nq, nr):
    q, r = cloud(nq, 1), cloud(nr, 2)
    d, i = g.nearest_neighbors(q, r)
    assert d.shape == (nq,) and i.shape == (nq,) and d.dtype == np.float32 and i.dtype == np.int64
    if nq * nr <= 4_000_000:
        assert_nearest_naive(q, r, d, i)
    # the distance is the float64 one of the point named, rounded to float32
    diff = q.astype(np.float64) - r[i]
    np.testing.assert_array_equal(
        d, (diff[:, 0] ** 2 + diff[:, 1] ** 2 + diff[:, 2] ** 2).astype(np.float32)
    )


@pytest.mark.parametrize("name", list(degenerate_clouds()))
def test_nearest_neighbors_on_degenerate_clouds(name):
    r = degenerate_clouds()[name]
    q = np.concatenate([r[:40], cloud(40, 3)])
    assert_nearest_naive(q, r, *g.nearest_neighbors(q, r))


@pytest.mark.parametrize("shape", ["plane", "line"])
@pytest.mark.parametrize(
    "heights", [[1e3], [1e5], [1.0, 1e3, -1e5, 30.0, 1e5, -1e3]], ids=["1e3", "1e5", "mixed"]
)
def test_nearest_neighbors_far_from_a_tilted_plane_or_line(shape, heights):
    # Audit K1: every point within about 2.5e-4 · H of a far query's foot ties with the nearest
    # in float32, which made such queries O(n); the float64 ranking separates them.
    query, reference = far_from_tilted(shape, 3000, heights, seed=11)
    assert_nearest_naive(query, reference, *g.nearest_neighbors(query, reference))
    np.testing.assert_allclose(
        g.chamfer(query, reference), chamfer_naive(query, reference), rtol=1e-12
    )


def test_nearest_neighbors_batched_and_mismatched_batches():
    q, r = (
        np.stack([cloud(30, s) for s in range(4)]),
        np.stack([cloud(50, s + 9) for s in range(4)]),
    )
    d, i = g.nearest_neighbors(q, r)
    assert d.shape == (4, 30)
    for b in range(4):
        assert_nearest_naive(q[b], r[b], d[b], i[b])
    with pytest.raises(ValueError, match=r"same size, got shapes \(4, 30, 3\) and \(3, 50, 3\)"):
        g.nearest_neighbors(q, r[:3])
    with pytest.raises(ValueError, match=r"query and reference must both be single clouds"):
        g.nearest_neighbors(q[0], r)


@pytest.mark.parametrize(("np_", "ng"), [(1, 1), (512, 2048), (3000, 100), (9000, 7000)])
def test_chamfer_matches_naive(np_, ng):
    p, t = cloud(np_, 4), cloud(ng, 5)
    got = g.chamfer(p, t)
    assert isinstance(got[0], float) and isinstance(got[1], float)
    if np_ * ng <= 5_000_000:
        np.testing.assert_allclose(got, chamfer_naive(p, t), rtol=1e-12)


def test_chamfer_identical_is_zero_and_shift_is_known():
    p = degenerate_clouds()["grid with ties"]
    assert g.chamfer(p, p) == (0.0, 0.0)
    # Shifting a unit grid by 0.25 along x: every nearest distance is 0.25 (squared 0.0625).
    shifted = p + np.float32([0.25, 0, 0])
    np.testing.assert_allclose(g.chamfer(shifted, p), (0.0625, 0.0625))


def test_chamfer_batched_float64_and_non_contiguous():
    p = np.stack([cloud(200, s) for s in range(6)])
    t = np.stack([cloud(300, s + 50) for s in range(6)])
    p2g, g2p = g.chamfer(p, t)
    assert p2g.shape == (6,) and p2g.dtype == np.float64
    for b in range(6):
        np.testing.assert_allclose((p2g[b], g2p[b]), chamfer_naive(p[b], t[b]), rtol=1e-12)
    p64 = np.asfortranarray(p.astype(np.float64))
    np.testing.assert_allclose(g.chamfer(p64, t)[0], p2g, rtol=1e-12)
    np.testing.assert_allclose(g.chamfer(p[:, ::2], t)[0][0], chamfer_naive(p[0, ::2], t[0])[0])


@settings(max_examples=40, deadline=None)
@given(
    hnp.arrays(
        np.float32, st.tuples(st.integers(1, 60), st.just(3)), elements=st.floats(-3, 3, width=32)
    ),
    hnp.arrays(
        np.float32, st.tuples(st.integers(1, 60), st.just(3)), elements=st.floats(-3, 3, width=32)
    ),
)
def test_chamfer_property(p, t):
    got = g.chamfer(p, t)
    np.testing.assert_allclose(got, chamfer_naive(p, t), rtol=1e-9, atol=0)
    assert min(got) >= 0


# ---------------------------------------------------------------- cropping


def test_viewpoints_are_the_authors_and_read_only():
    np.testing.assert_array_equal(
        g.VIEWPOINTS, [[1, 0, 0], [0, 0, 1], [1, 0, 1], [-1, 0, 0], [-1, 1, 0]]
    )
    assert g.VIEWPOINTS.dtype == np.float32
    with pytest.raises(ValueError, match="read-only"):
        g.VIEWPOINTS[0, 0] = 3


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("n_missing", [0, 1, 512, 1999])
def test_crop_by_count_matches_naive(dtype, n_missing):
    p = cloud(2000, 8, dtype)
    for v in g.VIEWPOINTS:
        partial, missing = g.crop_by_viewpoint(p, v, n_missing=n_missing)
        want_partial, want_missing = crop_naive(p, v, n_missing)
        assert partial.dtype == dtype and missing.shape == (n_missing, 3)
        np.testing.assert_array_equal(partial, want_partial)
        np.testing.assert_array_equal(missing, want_missing)


@pytest.mark.parametrize("name", list(degenerate_clouds()))
def test_crop_ties_go_to_the_lowest_index(name):
    p = degenerate_clouds()[name]
    for n_missing in sorted({0, min(1, len(p) - 1), len(p) // 3, len(p) - 1}):
        got = g.crop_by_viewpoint(p, [1, 0, 0], n_missing=n_missing)
        want = crop_naive(p, [1, 0, 0], n_missing)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])


def test_crop_batched_with_one_viewpoint_per_cloud_and_views():
    batch = np.stack([cloud(100, s) for s in range(5)])
    partial, missing = g.crop_by_viewpoint(batch, g.VIEWPOINTS, n_missing=25)
    assert partial.shape == (5, 75, 3) and missing.shape == (5, 25, 3)
    for b in range(5):
        want = crop_naive(batch[b], g.VIEWPOINTS[b], 25)
        np.testing.assert_array_equal(partial[b], want[0])
        np.testing.assert_array_equal(missing[b], want[1])
    shared = g.crop_by_viewpoint(batch[:, ::3], [0, 1, 0], n_missing=5)
    np.testing.assert_array_equal(shared[1][2], crop_naive(batch[2, ::3], [0, 1, 0], 5)[1])


def test_crop_by_radius():
    p = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], dtype=np.float64)
    partial, missing = g.crop_by_viewpoint(p, [0, 0, 0], radius=1.0)
    np.testing.assert_array_equal(missing, p[:2])
    np.testing.assert_array_equal(partial, p[2:])
    parts, misses = g.crop_by_viewpoint(np.stack([p, p + 1]), [[0, 0, 0], [0, 0, 0]], radius=1.5)
    assert [len(m) for m in misses] == [2, 0] and [len(q) for q in parts] == [2, 4]


def test_crop_multi_region_splits_the_count():
    p = np.array([[float(i), 0, 0] for i in range(20)], dtype=np.float32)
    partial, missing = g.crop_multi_region(p, [[-1, 0, 0], [30, 0, 0]], n_missing=5)
    np.testing.assert_array_equal(missing[:, 0], [0, 1, 2, 18, 19])
    assert len(partial) == 15
    # Regions that want the same points: the second region takes the next nearest.
    _, missing = g.crop_multi_region(p, [[-1, 0, 0], [-1, 0, 0]], n_missing=4)
    np.testing.assert_array_equal(missing[:, 0], [0, 1, 2, 3])


def test_random_crop_is_seeded_and_uses_the_viewpoints():
    p = cloud(1000, 2)
    a = g.random_crop(p, 250, seed=3)
    b = g.random_crop(p, 250, seed=3)
    np.testing.assert_array_equal(a[1], b[1])
    assert any(np.array_equal(a[1], crop_naive(p, v, 250)[1]) for v in g.VIEWPOINTS), (
        "a one-region crop must be the crop of one of the five viewpoints"
    )
    seen = {g.random_crop(p, 10, seed=s)[1].tobytes() for s in range(40)}
    assert len(seen) == 5
    batch = np.stack([p] * 8)
    partial, missing = g.random_crop(batch, 100, seed=1, n_regions=2, directions="sphere")
    assert partial.shape == (8, 900, 3) and len({m.tobytes() for m in missing}) > 1


@pytest.mark.parametrize(
    ("call", "error", "match"),
    [
        (
            lambda: g.crop_by_viewpoint(cloud(10), [1, 0, 0]),
            ValueError,
            "exactly one of n_missing or radius",
        ),
        (
            lambda: g.crop_by_viewpoint(cloud(10), [1, 0, 0], n_missing=2, radius=1),
            ValueError,
            "exactly one",
        ),
        (
            lambda: g.crop_by_viewpoint(cloud(10), [1, 0, 0], n_missing=10),
            ValueError,
            r"n_missing must be in 0\.\.9 .*shape \(10, 3\)\), got 10",
        ),
        (
            lambda: g.crop_by_viewpoint(cloud(10), [1, 0], n_missing=1),
            ValueError,
            r"viewpoint must have shape \(3,\), got \(2,\)",
        ),
        (
            lambda: g.crop_by_viewpoint(np.stack([cloud(10)] * 2), np.zeros((3, 3)), n_missing=1),
            ValueError,
            "3 rows for a batch of 2",
        ),
        (
            lambda: g.crop_by_viewpoint(cloud(10), [np.nan, 0, 0], n_missing=1),
            ValueError,
            "viewpoint must be finite",
        ),
        (
            lambda: g.crop_by_viewpoint(cloud(10), [0, 0, 0], radius=-1),
            ValueError,
            "radius must be a finite number >= 0",
        ),
        (
            lambda: g.crop_multi_region(cloud(10), np.zeros((0, 3)), 2),
            ValueError,
            "viewpoints is empty",
        ),
        (
            lambda: g.random_crop(cloud(10), 2, seed=0, n_regions=6),
            ValueError,
            r"n_regions must be in 1\.\.5",
        ),
        (
            lambda: g.random_crop(cloud(10), 2, seed=0, directions="up"),
            ValueError,
            "directions must be",
        ),
        (lambda: g.random_crop(cloud(10), 2, seed=-1), ValueError, r"seed must be an integer"),
        (lambda: g.random_crop(cloud(10), 2, seed=2**64), ValueError, r"in \[0, 2\*\*64\)"),
    ],
)
def test_crop_errors(call, error, match):
    with pytest.raises(error, match=match) as raised:
        call()
    assert isinstance(raised.value, GeometryError) == (error is ValueError)


def test_clouds_over_the_u32_limit_are_refused_before_any_copy():
    # A read-only view of 2^32 copies of one point: nothing is allocated, and the check must
    # come before the float32/C-order conversion that would copy it (48 GiB).
    assert g.MAX_POINTS == 2**32 - 1
    huge = np.broadcast_to(np.zeros(3, np.float32), (g.MAX_POINTS + 1, 3))
    batch = np.broadcast_to(np.zeros(3, np.float64), (2, g.MAX_POINTS + 1, 3))
    match = r"has 4294967296 points per cloud \(shape .*\), more than the 4294967295 \(2\^32 - 1\)"
    for name, call in [
        ("points", lambda: g.farthest_point_sample(huge, 1)),
        ("points", lambda: g.farthest_point_sample(batch, 1)),
        ("reference", lambda: g.nearest_neighbors(cloud(5), huge)),
        ("gt", lambda: g.chamfer(cloud(5), huge)),
        ("points", lambda: g.crop_by_viewpoint(huge, g.VIEWPOINTS[0], n_missing=1)),
        ("points", lambda: g.crop_multi_region(batch, g.VIEWPOINTS[:2], 1)),
        ("points", lambda: g.random_crop(huge, 1, seed=0)),
    ]:
        with pytest.raises(GeometryError, match=f"^{name} {match}"):
            call()


def test_no_rust_panic_escapes_on_odd_shapes():
    # Batches of zero clouds and single-point clouds are fine; they must not reach a panic.
    assert g.farthest_point_sample(np.zeros((0, 4, 3), np.float32), 2).shape == (0, 2)
    assert g.farthest_point_sample(np.zeros((1, 3)), 1).tolist() == [0]
    partial, missing = g.crop_by_viewpoint(np.zeros((1, 3)), [0, 0, 0], n_missing=0)
    assert partial.shape == (1, 3) and missing.shape == (0, 3)


def _batched_calls_in_child(queue):
    batch = np.stack([cloud(3000, s) for s in range(4)])
    idx = g.farthest_point_sample(batch, 16)
    partial, _ = g.crop_by_viewpoint(batch, g.VIEWPOINTS[:4], n_missing=100)
    d, _ = g.nearest_neighbors(batch, batch[::-1].copy())
    big = cloud(20000)
    queue.put((idx.shape, partial.shape, d.shape, g.chamfer(big, big)))


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # Python 3.12 warns on fork+threads
def test_batched_calls_work_in_a_forked_child_after_the_parent_used_the_pool():
    # A DataLoader worker under the default 'fork' start method inherits rayon's pool without
    # its threads: the core must notice and run sequentially instead of waiting forever.
    import multiprocessing

    g.farthest_point_sample(np.stack([cloud(3000, s) for s in range(4)]), 8)  # start the pool
    g.chamfer(cloud(20000), cloud(20000))
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_batched_calls_in_child, args=(queue,))
    child.start()
    child.join(timeout=60)
    hung = child.is_alive()
    if hung:
        child.kill()
    assert not hung, "batched geometry hung in a forked child"
    assert queue.get(timeout=5) == ((4, 16), (4, 2900, 3), (4, 3000), (0.0, 0.0))
