"""Geometry core beside the tools people use today, timed in the same process.

Run: ``python -m pytest benchmarks/bench_geometry.py --benchmark-only --benchmark-group-by=group``
(needs the ``bench`` extra: fpsample, pykdtree, scipy). Each group holds our function and its
anchor from DESIGN.md §6 on the same float32 cloud; compare the ``min`` or ``median`` columns.
"""

import numpy as np
import pytest

from pfnet import geometry as g

fpsample = pytest.importorskip("fpsample")
pykdtree = pytest.importorskip("pykdtree.kdtree")
cKDTree = pytest.importorskip("scipy.spatial").cKDTree

RNG = np.random.default_rng(0)


def cloud(*shape):
    return RNG.uniform(-1, 1, (*shape, 3)).astype(np.float32)


# ------------------------------------------------------------------ farthest point sampling
# fpsample is single-threaded with no batch API; our single-cloud IFPS is single-threaded too.
FPS_CASES = [(2048, 512, 3), (16384, 1024, 5), (100_000, 4096, 7)]


@pytest.mark.parametrize(("n", "k", "h"), FPS_CASES, ids=[f"{n}->{k}" for n, k, _ in FPS_CASES])
def test_fps_pfnet(benchmark, n, k, h):
    benchmark.group = f"fps {n}->{k}"
    p = cloud(n)
    idx = benchmark(g.farthest_point_sample, p, k)
    assert len(np.unique(idx)) == k


@pytest.mark.parametrize(("n", "k", "h"), FPS_CASES, ids=[f"{n}->{k}" for n, k, _ in FPS_CASES])
def test_fps_fpsample_kdline(benchmark, n, k, h):
    benchmark.group = f"fps {n}->{k}"
    p = cloud(n)
    idx = benchmark(fpsample.bucket_fps_kdline_sampling, p, k, h=h)
    assert len(np.unique(idx)) == k


def test_fps_batch36_pfnet(benchmark):
    benchmark.group = "fps batch 36x2048->512"
    b = cloud(36, 2048)
    assert benchmark(g.farthest_point_sample, b, 512).shape == (36, 512)


def test_fps_batch36_fpsample_loop(benchmark):
    benchmark.group = "fps batch 36x2048->512"
    b = cloud(36, 2048)

    def loop():
        return [fpsample.bucket_fps_kdline_sampling(c, 512, h=3) for c in b]

    assert len(benchmark(loop)) == 36


# ------------------------------------------------------------------ chamfer
def pykdtree_chamfer(pred, gt):
    """Both directed terms with pykdtree (OpenMP threads: all cores)."""
    out = []
    for p, t in zip(pred, gt):
        d_pg, _ = pykdtree.KDTree(t).query(p, k=1)
        d_gp, _ = pykdtree.KDTree(p).query(t, k=1)
        out.append(((d_pg.astype(np.float64) ** 2).mean(), (d_gp.astype(np.float64) ** 2).mean()))
    return out


def ckdtree_chamfer(pred, gt):
    out = []
    for p, t in zip(pred, gt):
        d_pg, _ = cKDTree(t).query(p, k=1, workers=-1)
        d_gp, _ = cKDTree(p).query(t, k=1, workers=-1)
        out.append(((d_pg**2).mean(), (d_gp**2).mean()))
    return out


CHAMFER_CASES = {"36 pairs of 2048": (36, 2048), "100k vs 100k": (1, 100_000)}


@pytest.mark.parametrize("case", CHAMFER_CASES)
@pytest.mark.parametrize("tool", ["pfnet", "pykdtree", "scipy-ckdtree"])
def test_chamfer(benchmark, case, tool):
    benchmark.group = f"chamfer {case}"
    b, n = CHAMFER_CASES[case]
    pred, gt = cloud(b, n), cloud(b, n)
    fn = {"pfnet": g.chamfer, "pykdtree": pykdtree_chamfer, "scipy-ckdtree": ckdtree_chamfer}[tool]
    result = benchmark(fn, pred, gt)
    assert len(result[0] if tool == "pfnet" else result) == b


def duplicated_cloud(kind: str, n: int = 100_000) -> np.ndarray:
    """``n`` points that are all one point, or copies of 20 points (a scan's repeated returns)."""
    rng = np.random.default_rng(7)
    centres = rng.uniform(-1, 1, (20, 3)).astype(np.float32)
    if kind == "identical":
        return np.repeat(centres[:1], n, axis=0)
    return centres[rng.integers(0, 20, n)]


# pykdtree and scipy take ~30 s on the identical case (pfnet took 29 s before it stored each
# distinct point once); the anchor is measured on the clustered case only.
@pytest.mark.parametrize(
    ("kind", "tool"),
    [("identical", "pfnet"), ("clustered", "pfnet"), ("clustered", "pykdtree")],
)
def test_chamfer_duplicates(benchmark, kind, tool):
    benchmark.group = f"chamfer 100k random vs 100k {kind}"
    reference = duplicated_cloud(kind)
    query = cloud(1, 100_000)[0]
    if tool == "pfnet":
        result = benchmark(g.chamfer, query, reference)
    else:
        result = benchmark(pykdtree_chamfer, [query], [reference])[0]
    assert np.isfinite(result[0])


def degenerate_pair(layout: str, n: int = 100_000) -> tuple[np.ndarray, np.ndarray]:
    """(query, reference) on which a KD-tree pfnet used went quadratic: kiddo's before issue 14,
    its own before audit 9 (oblique layouts) and before audit K1 (far from tilted ones)."""
    rng = np.random.default_rng(14)
    if layout == "collinear":
        line = np.zeros((n, 3), np.float32)
        line[:, 0] = np.arange(n) / n
        return line, line
    if layout == "far queries":
        reference = rng.uniform(0, 1, (n, 3)).astype(np.float32)
        return reference + np.float32(100), reference
    if layout == "tiny":  # float32 squared distances underflow to 0
        tiny = (rng.random((n, 3)) * 1e-25).astype(np.float32)
        return tiny, tiny
    # Audit 9 (G2): oblique layouts and far clusters were quadratic in pfnet's first own tree
    # (1M points: 54 s for the noisy line, 46 s for the plane) until its oriented hulls.
    if layout == "oblique line, noisy queries":
        t = rng.random(n)
        line = np.c_[t, t, t].astype(np.float32)
        return (line + rng.normal(0, 0.01, (n, 3))).astype(np.float32), line
    if layout == "oblique plane, cube queries":
        a, b = rng.random(n), rng.random(n)
        plane = np.c_[a, b, 1 - a - b].astype(np.float32)
        return rng.random((n, 3)).astype(np.float32), plane
    if layout == "two far tiny clusters":
        cluster = (rng.random((n, 3)) * 1e-6).astype(np.float32)
        cluster[n // 2 :] += np.float32(1e6)
        return rng.random((n, 3)).astype(np.float32) * np.float32(1e6), cluster
    # Audit K1: queries far from a tilted plane or line, where every point near a query's foot
    # ties in float32 (100k points at H = 1e3: 21 s when pfnet ranked in float32 first). A tenth
    # as many queries as points: scipy takes seconds.
    if layout.startswith("tilted "):
        shape, height = layout.split()[1].rstrip(","), layout.split()[-1]
        return far_from_tilted(shape, n, n // 10, float(height), rng)
    subnormal = (rng.random((n, 3)) * 1e-40).astype(np.float32)
    subnormal[-1] = 1e17
    return subnormal, subnormal


def far_from_tilted(
    shape: str, n: int, queries: int, height: float, rng
) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points on a tilted unit patch of a plane or unit segment of a line, and ``queries``
    queries ``height`` away from points of it (across the plane, or across the line)."""
    if shape == "plane":
        a, b = rng.random((2, n))
        reference = np.c_[a, b, 0.3 * a + 0.7 * b]
        fa, fb = rng.random((2, queries))
        feet = np.c_[fa, fb, 0.3 * fa + 0.7 * fb]
        away = np.array([0.3, 0.7, -1.0]) / np.sqrt(1.58)
    else:
        direction = np.array([1.0, 0.6, 0.3]) / np.sqrt(1.45)
        reference, feet = rng.random((n, 1)) * direction, rng.random((queries, 1)) * direction
        away = rng.normal(size=(queries, 3))
        away -= (away @ direction)[:, None] * direction
        away /= np.linalg.norm(away, axis=1, keepdims=True)
    return (feet + height * away).astype(np.float32), reference.astype(np.float32)


def ckdtree_nearest(query, reference):
    return cKDTree(reference).query(query, k=1, workers=-1)


DEGENERATE = [
    "collinear",
    "far queries",
    "tiny",
    "subnormal and one huge point",
    "oblique line, noisy queries",
    "oblique plane, cube queries",
    "two far tiny clusters",
    "tilted plane, queries at 1e3",
    "tilted plane, queries at 1e5",
    "tilted line, queries at 1e3",
    "tilted line, queries at 1e5",
]


# Before issue 14 pfnet took 1.4 s, 2.0 s, 10 s and 19 s on the first four (scipy 0.04-0.1 s).
@pytest.mark.parametrize("layout", DEGENERATE)
@pytest.mark.parametrize("tool", ["pfnet", "scipy-ckdtree"])
def test_nearest_degenerate(benchmark, layout, tool):
    benchmark.group = f"nearest neighbours 100k, {layout}"
    query, reference = degenerate_pair(layout)
    fn = {"pfnet": g.nearest_neighbors, "scipy-ckdtree": ckdtree_nearest}[tool]
    distances, _ = benchmark(fn, query, reference)
    assert len(distances) == len(query)


# ------------------------------------------------------------------ crop
def numpy_crop(points, viewpoint, n_missing):
    d = ((points - viewpoint) ** 2).sum(axis=1)
    mask = np.zeros(len(points), dtype=bool)
    mask[np.argpartition(d, n_missing)[:n_missing]] = True
    return points[~mask], points[mask]


@pytest.mark.parametrize("tool", ["pfnet", "numpy-argpartition"])
def test_crop_16k(benchmark, tool):
    benchmark.group = "crop 16384, one viewpoint, 25%"
    p = cloud(16384)
    if tool == "pfnet":
        partial, missing = benchmark(g.crop_by_viewpoint, p, g.VIEWPOINTS[0], n_missing=4096)
    else:
        partial, missing = benchmark(numpy_crop, p, g.VIEWPOINTS[0], 4096)
    assert missing.shape == (4096, 3)


def test_crop_batch36_pfnet(benchmark):
    benchmark.group = "crop batch 36x2048, test protocol"
    b = cloud(36, 2048)
    views = g.VIEWPOINTS[np.arange(36) % 5]
    assert benchmark(g.crop_by_viewpoint, b, views, n_missing=512)[1].shape == (36, 512, 3)


def test_crop_batch36_numpy_loop(benchmark):
    benchmark.group = "crop batch 36x2048, test protocol"
    b = cloud(36, 2048)
    views = g.VIEWPOINTS[np.arange(36) % 5]
    assert len(benchmark(lambda: [numpy_crop(c, v, 512) for c, v in zip(b, views)])) == 36
