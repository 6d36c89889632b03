"""The torch CompletionDataset: test-protocol crops and seeded random training crops."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from pfnet.data import load_split, test_protocol_crop  # noqa: E402
from pfnet.data.dataset import CompletionDataset  # noqa: E402
from pfnet.errors import ConfigError, DataError  # noqa: E402


def _sorted_rows(points: np.ndarray) -> np.ndarray:
    return points[np.lexsort(points.T[::-1])]


def test_test_crop_matches_the_protocol(tiny_dataset: Path) -> None:
    dataset = CompletionDataset(tiny_dataset, "test", missing_ratio=0.25, crop="test")
    clouds = load_split(tiny_dataset, "test")
    partial, missing = test_protocol_crop(clouds.points, 0.25)
    assert len(dataset) == 12 and dataset.n_missing == 128 and dataset.n_points == 512
    for i in range(len(dataset)):
        item = dataset[i]
        assert item["partial"].dtype == torch.float32 and item["partial"].shape == (384, 3)
        np.testing.assert_array_equal(item["partial"].numpy(), partial[i])
        np.testing.assert_array_equal(item["missing"].numpy(), missing[i])
        np.testing.assert_array_equal(item["complete"].numpy(), clouds.points[i])
        assert (item["category"], item["name"], item["index"]) == (
            clouds.category[i], clouds.name[i], i,
        )  # fmt: skip
    dataset.set_epoch(3)  # the test protocol does not depend on the epoch
    np.testing.assert_array_equal(dataset[4]["missing"].numpy(), missing[4])
    assert dataset.categories == ["chair", "lamp", "sofa", "table"]


def test_five_views_give_every_shape_all_five_test_crops(tiny_dataset: Path) -> None:
    from pfnet.geometry import VIEWPOINTS, crop_by_viewpoint

    clouds = load_split(tiny_dataset, "test")
    shape = CompletionDataset(tiny_dataset, "test", crop="test", views=5)
    scan = CompletionDataset(tiny_dataset, "test", crop="test", frame="scan", up_axis=1, views=5)
    one = CompletionDataset(tiny_dataset, "test", crop="test", frame="scan", up_axis=1)
    assert len(shape) == len(scan) == 5 * len(one) == 60 and scan.categories == one.categories
    for j in (0, 4, 7, 59):  # shape j // 5 cut at viewpoint j % 5
        expected, _ = crop_by_viewpoint(clouds.points[j // 5], VIEWPOINTS[j % 5], n_missing=128)
        item = shape[j]
        np.testing.assert_array_equal(item["partial"].numpy(), expected)
        assert item["name"] == f"{clouds.name[j // 5]}-v{j % 5}" and item["index"] == j
        turned = scan[j]  # the same cut, in a scan frame of its own: distances kept
        gaps = np.linalg.norm(expected[:40, None] - expected[None, :40], axis=-1)
        ours = turned["partial"].numpy()[:40].astype(np.float64) * float(turned["frame_radius"])
        np.testing.assert_allclose(
            np.linalg.norm(ours[:, None] - ours[None], axis=-1), gaps, atol=1e-5
        )
    np.testing.assert_array_equal(scan[0]["partial"].numpy(), one[0]["partial"].numpy())
    with pytest.raises(ConfigError, match="views = 5 cuts each shape at several viewpoints"):
        CompletionDataset(tiny_dataset, "train", crop="viewpoint", views=5)
    with pytest.raises(ConfigError, match="views must be 1 or 5"):
        CompletionDataset(tiny_dataset, "test", crop="test", views=2)


@pytest.mark.parametrize("crop", ["viewpoint", "turned", "sphere", "multi"])
def test_random_crops_are_seeded_by_seed_epoch_index(tiny_dataset: Path, crop: str) -> None:
    dataset = CompletionDataset(tiny_dataset, "train", missing_ratio=0.5, crop=crop, seed=7)
    twin = CompletionDataset(tiny_dataset, "train", missing_ratio=0.5, crop=crop, seed=7)
    first = [dataset[i]["missing"].numpy() for i in range(len(dataset))]
    for i in range(len(dataset)):
        np.testing.assert_array_equal(twin[i]["missing"].numpy(), first[i])
        np.testing.assert_array_equal(dataset[i]["missing"].numpy(), first[i])  # repeatable
        item = dataset[i]
        assert item["partial"].shape == (256, 3) and item["missing"].shape == (256, 3)
        union = np.concatenate([item["partial"].numpy(), item["missing"].numpy()])
        np.testing.assert_array_equal(_sorted_rows(union), _sorted_rows(item["complete"].numpy()))
    dataset.set_epoch(1)
    second = [dataset[i]["missing"].numpy() for i in range(len(dataset))]
    assert (
        sum(not np.array_equal(a, b) for a, b in zip(first, second, strict=True)) > len(first) // 2
    )
    other = CompletionDataset(tiny_dataset, "train", missing_ratio=0.5, crop=crop, seed=8)
    assert any(not np.array_equal(other[i]["missing"].numpy(), first[i]) for i in range(len(other)))


def test_turned_crop_is_a_viewpoint_crop_of_the_turned_shape_turned_back(
    tiny_dataset: Path,
) -> None:
    """The cut comes from a random side; the shape keeps its heading: the missing points are
    the ones nearest one of the five viewpoints turned about y (found by a search over 0.1°
    steps, a brute-force reference), and the turns differ from sample to sample."""
    from pfnet.data.scan_frame import up_rotation
    from pfnet.geometry import VIEWPOINTS

    dataset = CompletionDataset(tiny_dataset, "train", crop="turned", seed=1)
    plain = CompletionDataset(tiny_dataset, "train", crop="viewpoint", seed=1)
    angles = np.linspace(0, 2 * np.pi, 3600, endpoint=False)
    views = np.concatenate(
        [np.stack([up_rotation(a, 1) @ np.asarray(v, float) for a in angles]) for v in VIEWPOINTS]
    )  # (5 * 3600, 3): viewpoint k turned by angles[j] at row k * 3600 + j
    found = []
    for i in range(len(dataset)):
        item = dataset[i]
        complete, missing = item["complete"].numpy(), item["missing"].numpy()
        np.testing.assert_array_equal(complete, plain[i]["complete"].numpy())  # not turned
        dist = ((complete[None].astype(float) - views[:, None]) ** 2).sum(-1)
        nearest = np.sort(np.argsort(dist, axis=1, kind="stable")[:, : len(missing)], axis=1)
        wanted = np.sort([int(np.flatnonzero((complete == m).all(1))[0]) for m in missing])
        rows = np.flatnonzero((nearest == wanted).all(1))
        if len(rows):
            found.append(angles[rows[0] % len(angles)])
    assert len(found) >= 0.9 * len(dataset)
    assert len({round(float(a), 1) for a in found}) > len(found) // 2
    assert sum(min(a, 2 * np.pi - a) < 0.05 for a in found) < len(found) // 4


def test_viewpoint_crop_uses_one_of_the_five_viewpoints(tiny_dataset: Path) -> None:
    from pfnet.geometry import VIEWPOINTS, crop_by_viewpoint

    dataset = CompletionDataset(tiny_dataset, "train", crop="viewpoint", seed=1)
    used = set()
    for i in range(len(dataset)):
        item = dataset[i]
        matches = [
            k
            for k, view in enumerate(VIEWPOINTS)
            if np.array_equal(
                crop_by_viewpoint(item["complete"].numpy(), view, n_missing=128)[1],
                item["missing"].numpy(),
            )
        ]
        assert matches, f"sample {i} was not cropped at a viewpoint"
        used.add(matches[0])
    assert len(used) >= 3


def test_dataloader_batches(tiny_dataset: Path) -> None:
    loader = torch.utils.data.DataLoader(
        CompletionDataset(tiny_dataset, "val", crop="viewpoint"), batch_size=4
    )
    batch = next(iter(loader))
    assert batch["partial"].shape == (4, 384, 3) and batch["missing"].shape == (4, 128, 3)
    assert len(batch["name"]) == 4 and batch["index"].tolist() == [0, 1, 2, 3]


def test_dataset_errors(tiny_dataset: Path, tmp_path: Path) -> None:
    with pytest.raises(
        ConfigError, match="crop must be one of test, viewpoint, turned, sphere, multi"
    ):
        CompletionDataset(tiny_dataset, "train", crop="random")
    with pytest.raises(ConfigError, match="seed must be a non-negative integer"):
        CompletionDataset(tiny_dataset, "train", seed=-2)
    with pytest.raises(ConfigError, match="missing_ratio must be in"):
        CompletionDataset(tiny_dataset, "train", missing_ratio=1.2)
    with pytest.raises(DataError, match="split must be one of"):
        CompletionDataset(tiny_dataset, "dev")
    with pytest.raises(DataError, match="no such dataset folder"):
        CompletionDataset(tmp_path / "none", "train")
    dataset = CompletionDataset(tiny_dataset, "val")
    with pytest.raises(ConfigError, match="epoch must be a non-negative integer"):
        dataset.set_epoch(-1)
    with pytest.raises(IndexError, match="index 8 out of range for a dataset of 8 samples"):
        dataset[8]
    assert dataset[-1]["index"] == 7
    assert type(dataset[np.int64(2)]["index"]) is int


def test_fresh_points_draw_a_new_cloud_from_the_pool_each_epoch(tmp_path: Path) -> None:
    from pfnet.data import prepare_dataset

    data = tmp_path / "pooled"
    prepare_dataset(
        None, data, format="procedural", points=128, pool=512, count=3, workers=1, progress=False
    )
    clouds = load_split(data, "train")
    fresh = CompletionDataset(data, "train", crop="viewpoint", seed=3, fresh_points=True)
    fixed = CompletionDataset(data, "train", crop="viewpoint", seed=3)
    assert fresh.fresh_points and not fixed.fresh_points
    pool = np.concatenate([clouds.points[1], clouds.extra[1]])
    draws = [fresh[(epoch, 1)]["complete"].numpy() for epoch in (0, 1)]
    assert not np.array_equal(draws[0], draws[1])
    for draw in draws:
        assert draw.shape == (128, 3) and len(np.unique(draw, axis=0)) == 128
        assert (draw[:, None] == pool[None]).all(-1).any(1).all()  # every point from the pool
    assert np.array_equal(fresh[(1, 1)]["complete"].numpy(), draws[1])  # seeded
    assert np.array_equal(fixed[(1, 1)]["complete"].numpy(), clouds.points[1])
    # The test protocol always uses the stored cloud.
    test = CompletionDataset(data, "train", crop="test", fresh_points=True)
    assert not test.fresh_points
    assert np.array_equal(test[1]["complete"].numpy(), clouds.points[1])


def test_augmentation_is_seeded_and_does_what_it_says(tiny_dataset: Path) -> None:
    from pfnet.data.augment import Augmentation, up_axis_index
    from pfnet.data.format import read_manifest

    up = up_axis_index(read_manifest(tiny_dataset))
    assert up == 1  # procedural shapes are y-up
    clouds = load_split(tiny_dataset, "train")
    original = clouds.points[2].astype(np.float64)
    rotate = CompletionDataset(
        tiny_dataset, "train", crop="viewpoint", seed=5, augment=Augmentation(up_axis=up)
    )
    a = rotate.cloud(2, epoch=0).astype(np.float64)
    assert np.allclose(a[:, 1], original[:, 1], atol=1e-6)  # the up coordinate stays
    assert np.allclose(
        np.hypot(a[:, 0], a[:, 2]), np.hypot(original[:, 0], original[:, 2]), atol=1e-5
    )
    assert not np.allclose(a, original, atol=1e-3)
    assert np.array_equal(rotate.cloud(2, epoch=0), a.astype(np.float32))  # seeded
    assert not np.array_equal(rotate.cloud(2, epoch=1), rotate.cloud(2, epoch=0))
    item = rotate[(0, 2)]  # the crop is of the augmented cloud
    assert np.array_equal(item["complete"].numpy(), rotate.cloud(2, epoch=0))

    scale = Augmentation(scale=0.2)(original, np.random.default_rng(0)).astype(np.float64)
    factors = scale.std(axis=0) / original.std(axis=0)
    assert np.all((0.8 - 1e-6 <= factors) & (factors <= 1.2 + 1e-6)) and np.ptp(factors) > 0.01
    noisy = Augmentation(jitter=0.01)(original, np.random.default_rng(0)) - original
    assert 0.008 < noisy.std() < 0.012 and np.abs(noisy).max() <= 0.03 + 1e-6

    # Off by default and never on the test protocol.
    plain = CompletionDataset(tiny_dataset, "train", crop="viewpoint", seed=5)
    assert np.array_equal(plain.cloud(2, epoch=0), clouds.points[2])
    test = CompletionDataset(tiny_dataset, "train", crop="test", augment=Augmentation(up_axis=up))
    assert test.augment is None and np.array_equal(test[2]["complete"].numpy(), clouds.points[2])


def test_augmentation_errors() -> None:
    from pfnet.data.augment import Augmentation, up_axis_index
    from pfnet.errors import ConfigError

    with pytest.raises(ConfigError, match="manifest names it .* this one says 'as in the source'"):
        up_axis_index({"up_axis": "as in the source"})
    with pytest.raises(ConfigError, match=r"scale must be in \[0, 1\)"):
        Augmentation(scale=1.5)
    with pytest.raises(ConfigError, match=r"jitter must be in \[0, 0.1\]"):
        Augmentation(jitter=float("nan"))
