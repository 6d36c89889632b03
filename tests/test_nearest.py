"""The nearest training crop (pfnet.evaluation.nearest), a baseline of the scan protocol."""

from __future__ import annotations

import numpy as np
import pytest

from pfnet.data.scan_frame import up_rotation
from pfnet.evaluation import nearest
from pfnet.evaluation.nearest import crop_bank, descriptor, nearest_completion, nearest_crops
from pfnet.geometry import VIEWPOINTS, chamfer, crop_by_viewpoint


def _shapes(count: int = 4, n: int = 256) -> np.ndarray:
    rng = np.random.default_rng(3)
    out = []
    for k in range(count):
        cloud = rng.normal(size=(n, 3)) * [0.7, 0.25 + 0.1 * k, 0.35]
        cloud[: n // 4, 0] += 0.6  # a lump at one end: a heading to find
        out.append(cloud / np.linalg.norm(cloud, axis=1).max())
    return np.asarray(out, np.float32)


def test_a_scan_that_is_a_bank_crop_gets_that_crops_missing_points_in_its_own_pose() -> None:
    shapes = _shapes()
    bank = crop_bank(shapes, 64, turns=2, seed=0)
    assert bank.partials.shape == (4 * 2 * 5, nearest.SAMPLES, 3)
    assert bank.missing.shape == (40, 64, 3) and list(bank.shapes[:10]) == [0] * 10
    # crop 13: shape 1, its first turn, viewpoint 3; rebuild it and put it in a pose
    offset = np.random.default_rng(0).random(2)[1]
    turn = up_rotation(2 * np.pi * offset / 2, 1).astype(np.float32)
    partial, removed = crop_by_viewpoint(
        np.ascontiguousarray(shapes[1] @ turn.T),
        np.asarray(VIEWPOINTS[3], np.float32),
        n_missing=64,
    )
    pose = up_rotation(1.3, 1)
    scan = partial.astype(np.float64) @ pose.T * 2.5 + [1.0, -2.0, 0.5]
    got, index = nearest_completion(bank, scan)
    assert index == 13
    np.testing.assert_allclose(got, removed @ pose.T * 2.5 + [1.0, -2.0, 0.5], atol=1e-4)


def test_the_shortlist_of_the_whole_bank_is_the_exhaustive_search() -> None:
    """With a shortlist as long as the bank, the look-up is the brute-force one: the crop of
    least Chamfer distance over the bank and both half turns."""
    from pfnet.data.scan_frame import scan_frame

    shapes = _shapes()
    bank = crop_bank(shapes[:3], 64, turns=2, seed=1)
    rng = np.random.default_rng(9)
    scan = crop_by_viewpoint(shapes[3], np.asarray(VIEWPOINTS[0], np.float32), n_missing=64)[0]
    scan = scan.astype(np.float64) @ up_rotation(rng.uniform(0, 6), 1).T
    _, index = nearest_completion(bank, scan, shortlist=len(bank.shapes))
    seen = scan_frame(scan, aligned=True).apply(scan)
    best = min(
        (
            sum(
                chamfer(nearest._samples(seen @ up_rotation(np.pi * h, 1).T.astype(np.float32)), c)
            ),
            j,
        )
        for h in (0, 1)
        for j, c in enumerate(bank.partials)
    )
    assert index == best[1]


def test_the_nearest_crops_are_the_exhaustive_ranking_best_first() -> None:
    """``nearest_crops`` with the whole bank shortlisted: the ``count`` least Chamfer distances
    over the bank and both half turns, in order, each with the turn that makes its distance."""
    from pfnet.data.scan_frame import scan_frame

    shapes = _shapes()
    bank = crop_bank(shapes[:3], 64, turns=2, seed=1)
    scan = crop_by_viewpoint(shapes[3], np.asarray(VIEWPOINTS[2], np.float32), n_missing=64)[0]
    seen = scan_frame(scan, aligned=True).apply(scan)
    found = nearest_crops(bank, seen, 5, shortlist=len(bank.shapes))
    brute = sorted(
        float(sum(chamfer(nearest._samples(seen @ up_rotation(np.pi * h, 1).T), c)))
        for h in (0, 1)
        for c in bank.partials
    )
    assert len(found) == 5
    np.testing.assert_allclose([d for d, _, _ in found], brute[:5], rtol=1e-5)
    for distance, index, turn in found:
        query = nearest._samples(seen @ turn.T)
        assert float(sum(chamfer(query, bank.partials[index]))) == pytest.approx(distance, 1e-5)
    assert nearest_crops(bank, seen, 1000, shortlist=4)[-1][0] >= found[0][0]
    assert len(nearest_crops(bank, seen, 1000, shortlist=4)) == 8  # both turns' shortlists


def test_the_descriptor_is_the_root_of_the_cells_shares() -> None:
    points = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [1.1, 1.1, 1.1], [5.0, 5.0, 5.0]])
    d = descriptor(points)
    assert d.shape == (nearest.GRID**3,)
    np.testing.assert_allclose((d**2).sum(), 1.0, rtol=1e-6)
    assert d.max() == np.float32(np.sqrt(0.5))  # the two points near the centre share a cell
    assert d[-1] == np.float32(np.sqrt(0.5))  # 1.1 and the clipped far point: the last cell


def test_the_scan_protocol_scores_the_spread_of_its_scans() -> None:
    from scripts import load_script

    script = load_script("scan_protocol")
    rng = np.random.default_rng(0)
    removed = rng.normal(size=(20, 32, 3)).astype(np.float32)
    predictions = [r + (2.0 if i == 0 else 0.001) for i, r in enumerate(removed)]
    table = script.score(predictions, removed, ["a"] * 10 + ["b"] * 10)
    spread = table["spread"]
    assert spread["median_cd_l2"] < 0.01 and len(spread["worst_cd_l2"]) == 2
    assert spread["worst_tenth_share"] > 0.99  # one scan 2 away makes the whole mean
    assert spread["worst_cd_l2"][0] == pytest.approx(
        table["categories"]["a"]["cd_l2"] * 10, rel=1e-4
    )
    assert "worst_scans" not in spread  # no labels given
    # with labels, the worst tenth by name, worst first (scan 0, then the next worst)
    predictions[7] = removed[7] + 0.5
    labels = [f"scan{i}" for i in range(20)]
    named = script.score(predictions, removed, ["a"] * 10 + ["b"] * 10, labels)["spread"]
    assert named["worst_scans"] == ["scan0", "scan7"]
    assert named["worst_cd_l2"][0] > named["worst_cd_l2"][1]
