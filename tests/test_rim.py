"""pfnet.data.rim and the frames that use it: the numpy edge score against the torch one, and
the ``rim`` / ``aligned-rim`` frames putting a cut's hole on +x."""

from __future__ import annotations

import numpy as np
import pytest

from pfnet.data.rim import RIM_POINTS, edge_scores, rim_centroid
from pfnet.data.scan_frame import frame_of, up_rotation


def _naive_edge_scores(points: np.ndarray, k: int) -> np.ndarray:
    """The edge score point by point, sorting every distance (the reference)."""
    out = []
    for i, p in enumerate(points):
        d = np.linalg.norm(points - p, axis=1)
        d[i] = -1.0  # the point itself first
        near = np.argsort(d, kind="stable")[1 : k + 1]
        out.append(np.linalg.norm(points[near].mean(axis=0) - p) / d[near].mean())
    return np.minimum(np.array(out), 1.0)


def test_edge_scores_match_the_naive_reference_and_the_networks() -> None:
    torch = pytest.importorskip("torch")
    from pfnet.models.edge import edge_scores as torch_edge_scores

    points = np.random.default_rng(0).normal(size=(1500, 3))  # more rows than one block
    ours = edge_scores(points, 32)
    np.testing.assert_allclose(ours, _naive_edge_scores(points, 32), atol=1e-9)
    theirs = torch_edge_scores(torch.from_numpy(points)[None])[0].numpy()
    np.testing.assert_allclose(ours, theirs, atol=1e-9)


def test_edge_scores_of_tiny_clouds() -> None:
    assert edge_scores(np.zeros((1, 3))).tolist() == [0.0]
    two = edge_scores(np.array([[0.0, 0, 0], [1.0, 0, 0]]))
    np.testing.assert_allclose(two, [1.0, 1.0])  # one neighbour: all to one side


def _cut_sphere(n: int = 3000, seed: int = 0) -> np.ndarray:
    """The unit sphere's surface with the cap beyond x = 0.5 cut away, as a viewpoint's ball
    cuts a shape: the rim is the ring at x = 0.5 (a sphere has no edge of its own)."""
    d = np.random.default_rng(seed).normal(size=(n, 3))
    surface = d / np.linalg.norm(d, axis=1, keepdims=True)
    return surface[surface[:, 0] < 0.5]


def test_the_rim_of_a_cut_lies_on_its_side() -> None:
    cut = _cut_sphere()
    assert rim_centroid(cut)[0] > cut[:, 0].mean() + 0.4


def test_a_large_cloud_has_its_rim_found_on_a_sample() -> None:
    cut = _cut_sphere(4 * RIM_POINTS, seed=1)
    assert len(cut) > RIM_POINTS
    assert rim_centroid(cut)[0] > cut[:, 0].mean() + 0.4


@pytest.mark.parametrize("angle", [0.0, 1.0, 2.5, -2.0])
def test_the_rim_frame_puts_the_hole_of_a_turned_cut_on_plus_x(angle: float) -> None:
    turned = _cut_sphere(seed=2) @ up_rotation(angle, 1).T
    hole_direction = np.array([1.0, 0.0, 0.0]) @ up_rotation(angle, 1).T
    mapped = hole_direction @ frame_of(turned, "rim").rotation.T
    assert mapped[0] > 0.9, mapped


@pytest.mark.parametrize("angle", [0.0, 1.0, 2.5, -2.0])
def test_the_aligned_rim_frame_turns_with_the_scan(angle: float) -> None:
    # a cut sphere stretched along z: its main axis is z, and the rim (at +x) is a quarter
    # turn from it; the frame takes the rim's side to +x whichever way the scan is turned
    cut = _cut_sphere(seed=3) * [1.0, 1.0, 1.6]
    turned = cut @ up_rotation(angle, 1).T
    hole_direction = np.array([1.0, 0.0, 0.0]) @ up_rotation(angle, 1).T
    mapped = hole_direction @ frame_of(turned, "aligned-rim").rotation.T
    assert mapped[0] > 0.9, mapped
