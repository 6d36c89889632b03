"""Benchmark ``pfnet evaluate``: 3,000 prediction files of 512 points against 2,048-point clouds.

Run on demand (not part of the test suite)::

    python -m pytest benchmarks/bench_evaluate.py --benchmark-only -p no:cacheprovider

The whole command (list the folder, read 3,000 ``.npy`` files with a thread pool, crop the
ground truth with the test protocol, Chamfer/F-score in the Rust core, per-category summary)
is timed beside its parts and beside the same metrics computed with scipy's cKDTree in a
Python loop (what a per-file evaluation script does).
"""

from __future__ import annotations

import numpy as np
import pytest

from pfnet.data import test_protocol_crop
from pfnet.data.format import SPLITS, CloudSet, write_dataset
from pfnet.evaluation.metrics import sample_metrics
from pfnet.evaluation.scoring import evaluate_predictions, find_prediction_files
from pfnet.io.clouds import read_point_cloud, save_npy

N_SAMPLES, N_POINTS, RATIO = 3000, 2048, 0.25
CATEGORIES = [f"cat{k:02d}" for k in range(13)]


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    """A data set whose test split has 3,000 shapes, and a prediction folder for it."""
    root = tmp_path_factory.mktemp("bench-evaluate")
    rng = np.random.default_rng(0)
    points = rng.normal(size=(N_SAMPLES, N_POINTS, 3))
    points /= np.linalg.norm(points, axis=2, keepdims=True).max(axis=1, keepdims=True)
    category = np.array([CATEGORIES[i % len(CATEGORIES)] for i in range(N_SAMPLES)])
    name = np.array([f"shape_{i:05d}" for i in range(N_SAMPLES)])
    test = CloudSet(points.astype(np.float32), category, name)
    splits = {s: (test if s == "test" else CloudSet.empty(N_POINTS)) for s in SPLITS}
    data = write_dataset(
        root / "data", splits, {"format": "pfnet-completion-dataset", "version": 1}
    )
    _, removed = test_protocol_crop(test.points, RATIO)
    pred = root / "pred"
    for cat in CATEGORIES:
        (pred / cat).mkdir(parents=True)
    noise = rng.normal(scale=0.01, size=removed.shape).astype(np.float32)
    for i in range(N_SAMPLES):
        save_npy(pred / category[i] / f"{name[i]}.npy", removed[i] + noise[i])
    return data, pred, removed


def test_evaluate_3000_predictions(benchmark, folders):
    data, pred, _ = folders
    result = benchmark.pedantic(
        evaluate_predictions, args=(pred, data), kwargs={"missing_ratio": RATIO}, rounds=3
    )
    assert sum(c["n"] for c in result.report["categories"].values()) == N_SAMPLES


def test_read_3000_files_threaded(benchmark, folders):
    from concurrent.futures import ThreadPoolExecutor

    _, pred, _ = folders

    def read_all():
        files = list(find_prediction_files(pred).values())
        with ThreadPoolExecutor(max_workers=6) as pool:
            return list(pool.map(read_point_cloud, files, chunksize=64))

    clouds = benchmark.pedantic(read_all, rounds=3)
    assert len(clouds) == N_SAMPLES


def test_metrics_3000_pairs_rust(benchmark, folders):
    _, _, removed = folders
    pred = removed + np.float32(0.01)
    result = benchmark.pedantic(sample_metrics, args=(pred, removed), rounds=3)
    assert result["cd_l2"].shape == (N_SAMPLES,)


def test_metrics_3000_pairs_scipy_loop(benchmark, folders):
    cKDTree = pytest.importorskip("scipy.spatial").cKDTree
    _, _, removed = folders
    pred = removed + np.float32(0.01)

    def scipy_loop():
        out = np.empty((N_SAMPLES, 2))
        for i in range(N_SAMPLES):
            d_pg, _ = cKDTree(removed[i]).query(pred[i], workers=2)
            d_gp, _ = cKDTree(pred[i]).query(removed[i], workers=2)
            out[i] = (d_pg**2).mean(), (d_gp**2).mean()
        return out

    out = benchmark.pedantic(scipy_loop, rounds=1)
    assert out.shape == (N_SAMPLES, 2)
