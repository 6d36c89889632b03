"""Type stubs of the private Rust extension; use ``pfnet.geometry`` instead."""

import numpy as np
from numpy.typing import NDArray

VIEWPOINTS: NDArray[np.float64]
MAX_REGIONS: int
MAX_COORDINATE: float
MAX_POINTS: int

class GeometryError(ValueError):
    """Every error the core raises (shapes, layouts, sizes, counts, coordinates); its public
    name is ``pfnet.errors.GeometryError``."""

def farthest_point_sample(
    points: NDArray[np.float32], n_samples: int, start_index: int
) -> NDArray[np.int64]: ...
def nearest_neighbors(
    query: NDArray[np.float32], reference: NDArray[np.float32]
) -> tuple[NDArray[np.float32], NDArray[np.int64]]: ...
def chamfer(
    pred: NDArray[np.float32], gt: NDArray[np.float32]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...
def minimal_matching(
    points: NDArray[np.float32], counts: list[int], references: NDArray[np.float32]
) -> tuple[NDArray[np.float64], NDArray[np.int64]]: ...
def crop_count_f32(
    points: NDArray[np.float32], viewpoints: NDArray[np.float64], n_missing: int
) -> tuple[NDArray[np.float32], NDArray[np.float32]]: ...
def crop_count_f64(
    points: NDArray[np.float64], viewpoints: NDArray[np.float64], n_missing: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...
def crop_radius_f32(
    points: NDArray[np.float32], viewpoint: list[float], radius: float
) -> tuple[NDArray[np.float32], NDArray[np.float32]]: ...
def crop_radius_f64(
    points: NDArray[np.float64], viewpoint: list[float], radius: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...
def crop_multi_f32(
    points: NDArray[np.float32], viewpoints: NDArray[np.float64], n_missing: int
) -> tuple[NDArray[np.float32], NDArray[np.float32]]: ...
def crop_multi_f64(
    points: NDArray[np.float64], viewpoints: NDArray[np.float64], n_missing: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...
def random_centres(
    seed: int, batch: int, n_regions: int, directions: str
) -> NDArray[np.float64]: ...
def lzf_decompress(data: NDArray[np.uint8], size: int) -> NDArray[np.uint8]: ...
