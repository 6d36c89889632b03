"""Every error path of the Rust core raises ``pfnet.errors.GeometryError``, a ``ValueError``.

The core is called directly here, with input that ``pfnet.geometry`` would refuse first, so that
each of its own checks is reached; ``tests/test_geometry.py`` covers the public functions.
"""

from __future__ import annotations

import pickle

import numpy as np
import pytest

import pfnet.errors
from pfnet import _core
from pfnet.errors import GeometryError
from pfnet.geometry import random_crop

F32 = np.float32


def _cloud(n: int, batch: int = 1, dtype=F32) -> np.ndarray:
    rng = np.random.default_rng(n)
    return rng.uniform(-1, 1, size=(batch, n, 3)).astype(dtype)


def _with(array: np.ndarray, index: tuple, value: float) -> np.ndarray:
    array = array.copy()
    array[index] = value
    return array


VIEW = np.array([[1.0, 0.0, 0.0]])

CASES = {
    # farthest_point_sample
    "fps shape": (
        lambda: _core.farthest_point_sample(np.zeros((1, 5, 2), F32), 1, 0),
        r"^points must have shape \(B, N, 3\), got \(1, 5, 2\)$",
    ),
    "fps layout": (
        lambda: _core.farthest_point_sample(_cloud(10)[:, ::2], 1, 0),
        r"^points must be C-contiguous$",
    ),
    # Fortran order is contiguous too, but its values would be read transposed
    "fps Fortran order": (
        lambda: _core.farthest_point_sample(np.asfortranarray(_cloud(10)), 2, 0),
        r"^points must be C-contiguous$",
    ),
    "fps empty": (
        lambda: _core.farthest_point_sample(np.zeros((1, 0, 3), F32), 1, 0),
        r"^points is empty: a cloud needs at least one point$",
    ),
    "fps many empty clouds": (
        lambda: _core.farthest_point_sample(np.zeros((2**40, 0, 3), F32), 1, 0),
        r"^points is empty",
    ),
    "fps n_samples": (
        lambda: _core.farthest_point_sample(_cloud(5), 6, 0),
        r"^n_samples must be in 1\.\.=5 \(the number of points\), got 6$",
    ),
    "fps no samples": (
        lambda: _core.farthest_point_sample(_cloud(5), 0, 0),
        r"^n_samples must be in 1\.\.=5",
    ),
    "fps start_index": (
        lambda: _core.farthest_point_sample(_cloud(5), 2, 5),
        r"^start_index must be in 0\.\.5 \(the number of points\), got 5$",
    ),
    "fps no clouds, huge n_samples": (
        lambda: _core.farthest_point_sample(np.zeros((0, 4, 3), F32), 2**62, 0),
        r"^n_samples must be in 1\.\.=4 \(the number of points\), got 4611686018427387904$",
    ),
    "fps no clouds, no points": (
        lambda: _core.farthest_point_sample(np.zeros((0, 0, 3), F32), 1, 0),
        r"^points is empty",
    ),
    "fps NaN": (
        lambda: _core.farthest_point_sample(_with(_cloud(5, 2), (1, 2, 0), np.nan), 2, 0),
        r"^points contains NaN or infinite coordinates \(first at batch 1, point 2\)$",
    ),
    "fps huge": (
        lambda: _core.farthest_point_sample(_with(_cloud(5), (0, 3, 2), 1e30), 2, 0),
        r"^points has a coordinate beyond ±1e18 \(first at batch 0, point 3\)",
    ),
    # nearest_neighbors and chamfer
    "nn batches": (
        lambda: _core.nearest_neighbors(_cloud(4, 2), _cloud(4, 3)),
        r"^query and reference must have the same batch size, got 2 and 3$",
    ),
    "nn shape": (
        lambda: _core.nearest_neighbors(_cloud(4), np.zeros((1, 4, 4), F32)),
        r"^reference must have shape \(B, N, 3\), got \(1, 4, 4\)$",
    ),
    "nn layout": (
        lambda: _core.nearest_neighbors(np.asfortranarray(_cloud(4)), _cloud(4)),
        r"^query must be C-contiguous$",
    ),
    "nn empty query": (
        lambda: _core.nearest_neighbors(np.zeros((1, 0, 3), F32), _cloud(4)),
        r"^query is empty",
    ),
    "nn empty reference": (
        lambda: _core.nearest_neighbors(_cloud(4), np.zeros((1, 0, 3), F32)),
        r"^reference is empty",
    ),
    "nn many empty clouds": (
        lambda: _core.nearest_neighbors(np.zeros((2**59, 0, 3), F32), np.zeros((2**59, 0, 3), F32)),
        r"^query is empty",
    ),
    "nn infinite": (
        lambda: _core.nearest_neighbors(_cloud(4), _with(_cloud(6), (0, 5, 1), np.inf)),
        r"^reference contains NaN or infinite coordinates \(first at batch 0, point 5\)$",
    ),
    "chamfer batches": (
        lambda: _core.chamfer(_cloud(4, 3), _cloud(4, 2)),
        r"^pred and gt must have the same batch size, got 3 and 2$",
    ),
    "chamfer empty": (
        lambda: _core.chamfer(_cloud(4), np.zeros((1, 0, 3), F32)),
        r"^gt is empty",
    ),
    "chamfer NaN in a batch": (
        lambda: _core.chamfer(_cloud(4, 3), _with(_cloud(6, 3), (2, 0, 0), np.nan)),
        r"^gt contains NaN or infinite coordinates \(first at batch 2, point 0\)$",
    ),
    # crop by count
    "count n_missing": (
        lambda: _core.crop_count_f32(_cloud(4), VIEW, 4),
        r"^n_missing must be smaller than the number of points \(4\), got 4$",
    ),
    "count empty": (
        lambda: _core.crop_count_f64(np.zeros((1, 0, 3)), VIEW, 0),
        r"^points is empty",
    ),
    "count shape": (
        lambda: _core.crop_count_f32(np.zeros((1, 4, 2), F32), VIEW, 1),
        r"^points must have shape \(B, N, 3\), got \(1, 4, 2\)$",
    ),
    "count viewpoint shape": (
        lambda: _core.crop_count_f32(_cloud(4), np.zeros((1, 2)), 1),
        r"^viewpoint must have shape \(B, 3\), got \(1, 2\)$",
    ),
    "count viewpoint rows": (
        lambda: _core.crop_count_f32(_cloud(4), np.zeros((2, 3)), 1),
        r"^points and viewpoint must have the same batch size, got 1 and 2$",
    ),
    "count viewpoint layout": (
        lambda: _core.crop_count_f32(_cloud(4, 2), np.zeros((2, 6))[:, ::2], 1),
        r"^viewpoint must be C-contiguous$",
    ),
    "count viewpoint Fortran order": (
        lambda: _core.crop_count_f32(_cloud(4, 2), np.asfortranarray(np.zeros((2, 3))), 1),
        r"^viewpoint must be C-contiguous$",
    ),
    "count viewpoint NaN": (
        lambda: _core.crop_count_f64(_cloud(4, dtype=np.float64), np.full((1, 3), np.nan), 1),
        r"^viewpoint must be finite, got \[NaN, NaN, NaN\]$",
    ),
    "count NaN in a batch": (
        lambda: _core.crop_count_f32(_with(_cloud(8, 2), (1, 3, 1), np.nan), VIEW[[0, 0]], 2),
        r"^points contains NaN or infinite coordinates \(first at batch 1, point 3\)$",
    ),
    "count huge": (
        lambda: _core.crop_count_f64(_with(_cloud(8, dtype=np.float64), (0, 6, 0), 1e300), VIEW, 2),
        r"^points has a coordinate beyond ±1e18 \(first at batch 0, point 6\)",
    ),
    # crop by radius
    "radius shape": (
        lambda: _core.crop_radius_f32(np.zeros((4, 2), F32), [0.0, 0.0, 0.0], 1.0),
        r"^points must have shape \(N, 3\), got \(4, 2\)$",
    ),
    "radius layout": (
        lambda: _core.crop_radius_f32(_cloud(10)[0, ::2], [0.0, 0.0, 0.0], 1.0),
        r"^points must be C-contiguous$",
    ),
    "radius Fortran order": (
        lambda: _core.crop_radius_f32(np.asfortranarray(_cloud(4)[0]), [0.0, 0.0, 0.0], 1.0),
        r"^points must be C-contiguous$",
    ),
    "radius empty": (
        lambda: _core.crop_radius_f64(np.zeros((0, 3)), [0.0, 0.0, 0.0], 1.0),
        r"^points is empty",
    ),
    "radius negative": (
        lambda: _core.crop_radius_f32(_cloud(4)[0], [0.0, 0.0, 0.0], -1.0),
        r"^radius must be a finite non-negative number, got -1$",
    ),
    "radius viewpoint": (
        lambda: _core.crop_radius_f32(_cloud(4)[0], [np.inf, 0.0, 0.0], 1.0),
        r"^viewpoint must be finite",
    ),
    "radius NaN": (
        lambda: _core.crop_radius_f64(
            _with(_cloud(4, dtype=np.float64)[0], (1, 2), np.nan), [0.0, 0.0, 0.0], 1.0
        ),
        r"^points contains NaN or infinite coordinates \(first at batch 0, point 1\)$",
    ),
    # crop around several viewpoints
    "multi viewpoints shape": (
        lambda: _core.crop_multi_f32(_cloud(8), np.zeros((1, 2, 2)), 2),
        r"^viewpoints must have shape \(B, K, 3\), got \(1, 2, 2\)$",
    ),
    "multi batches": (
        lambda: _core.crop_multi_f32(_cloud(8, 2), np.zeros((3, 1, 3)), 2),
        r"^points and viewpoints must have the same batch size, got 2 and 3$",
    ),
    "multi viewpoints Fortran order": (
        lambda: _core.crop_multi_f32(_cloud(8, 2), np.asfortranarray(np.zeros((2, 2, 3))), 2),
        r"^viewpoints must be C-contiguous$",
    ),
    "multi no viewpoints": (
        lambda: _core.crop_multi_f32(_cloud(8), np.zeros((1, 0, 3)), 2),
        r"^viewpoints is empty",
    ),
    "multi viewpoint NaN": (
        lambda: _core.crop_multi_f64(_cloud(8, dtype=np.float64), np.full((1, 2, 3), np.nan), 2),
        r"^viewpoint must be finite",
    ),
    "multi n_missing": (
        lambda: _core.crop_multi_f32(_cloud(8), np.zeros((1, 2, 3)), 9),
        r"^n_missing must be smaller than the number of points \(8\), got 9$",
    ),
    "multi NaN in a batch": (
        lambda: _core.crop_multi_f32(
            _with(_cloud(8, 2), (1, 7, 2), np.nan), np.zeros((2, 2, 3)), 2
        ),
        r"^points contains NaN or infinite coordinates \(first at batch 1, point 7\)$",
    ),
    # random centres
    "centres directions": (
        lambda: _core.random_centres(0, 1, 1, "up"),
        r"""^directions must be 'viewpoints' or 'sphere', got "up"$""",
    ),
    "centres no regions": (
        lambda: _core.random_centres(0, 0, 0, "sphere"),
        r"^n_regions must be in \[1, 256\], got 0$",
    ),
    "centres huge batch": (
        lambda: _core.random_centres(0, 2**60, 1, "sphere"),
        r"^batch is too large: 1152921504606846976 × 1 centres do not fit in memory$",
    ),
    "centres impossible batch": (
        lambda: _core.random_centres(0, 2**40, 5, "viewpoints"),
        r"^batch is too large",
    ),
    "centres six viewpoints": (
        lambda: _core.random_centres(0, 1, 6, "viewpoints"),
        r"^n_regions must be at most 5 with directions='viewpoints', got 6$",
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_every_core_error_is_a_geometry_error_naming_the_argument(case: str) -> None:
    call, match = CASES[case]
    with pytest.raises(ValueError, match=match) as raised:
        call()
    assert type(raised.value) is GeometryError


def test_geometry_error_is_one_class_exported_from_pfnet_errors() -> None:
    assert pfnet.errors.GeometryError is _core.GeometryError
    assert issubclass(GeometryError, ValueError)
    assert not issubclass(GeometryError, pfnet.errors.PfnetError)
    assert GeometryError.__module__ == "pfnet.errors"
    assert GeometryError.__name__ == "GeometryError"
    assert GeometryError.__doc__


def test_geometry_errors_survive_pickling() -> None:
    # multiprocessing pickles exceptions raised in workers by their class's qualified name
    with pytest.raises(GeometryError) as raised:
        _core.farthest_point_sample(np.zeros((1, 0, 3), F32), 1, 0)
    copy = pickle.loads(pickle.dumps(raised.value))
    assert type(copy) is GeometryError and copy.args == raised.value.args


def test_the_point_limit_is_u32() -> None:
    assert _core.MAX_POINTS == 2**32 - 1


def test_a_huge_broadcast_batch_is_refused_not_allocated() -> None:
    # A read-only view claiming 2^40 clouds: the crop centres for it cannot exist, and the core
    # says so instead of aborting the process on the allocation.
    batch = np.broadcast_to(np.zeros(3, F32), (2**40, 16, 3))
    with pytest.raises(GeometryError, match=r"^batch is too large: 1099511627776 × 1 centres"):
        random_crop(batch, 4, seed=0)
