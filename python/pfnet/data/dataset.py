"""The torch ``Dataset`` of completion samples, cropped on the fly by the Rust core."""

from __future__ import annotations

import operator
import os

import numpy as np
import torch
from torch.utils.data import Dataset

from pfnet.data.augment import Augmentation, up_axis_index
from pfnet.data.crops import every_view, missing_count, test_protocol_viewpoints
from pfnet.data.format import CloudSet, load_split, read_manifest
from pfnet.data.scan_frame import FRAMES, frame_of, scan_angle, scan_frame, up_rotation
from pfnet.data.scanner import scanner_sample, test_sample_rng
from pfnet.errors import ConfigError, DataError

__all__ = ["CROPS", "TEST_CROPS", "CompletionDataset", "validation_crop"]

CROPS: tuple[str, ...] = (
    "test",
    "viewpoint",
    "turned",
    "sphere",
    "multi",
    "scanner",
    "scanner-test",
)
"""Crop modes: the deterministic test protocol, one random viewpoint of the five (the
authors' training crop), one random direction on the unit sphere, two random viewpoints, a
depth camera's view from a random position (:mod:`pfnet.data.scanner`), or the scanner's
deterministic test protocol."""

TEST_CROPS: tuple[str, ...] = ("test", "scanner-test")
"""The deterministic crops: no fresh points, no augmentation, the same samples every epoch."""


def validation_crop(train_crop: str) -> str:
    """The deterministic crop that validates a run trained with ``train_crop``: the scanner
    test protocol for the scanner crop, the paper's test protocol for the others."""
    return "scanner-test" if train_crop == "scanner" else "test"


_MULTI_REGIONS = 2  # paper §4.4: pieces lost "in two random positions"


def _heading_frame(partial: np.ndarray, up_axis: int, what: str):
    """The ``heading`` frame of a turned test partial: the scan frame turned back by the
    heading the shipped reader reads (:mod:`pfnet.data.heading`, trained y-up)."""
    from pfnet.data.heading import load_reader

    if up_axis != 1:
        raise ConfigError(
            f"{what}: the heading frame reads y-up partials; this data set's up axis is "
            f"{'xyz'[up_axis]}"
        )
    base = scan_frame(partial, up_axis=1)
    (heading,) = load_reader().headings([base.apply(partial)])
    return scan_frame(partial, up_axis=1, heading=heading)


def _manifest_up_axis(root: str | os.PathLike[str]) -> int:
    """The data set's up axis from its manifest (y, the prepared sources', when it names
    none: a mesh folder "as in the source")."""
    try:
        return up_axis_index(read_manifest(root))
    except ConfigError:
        return 1


class CompletionDataset(Dataset):
    """Completion samples of one split: the complete cloud, the partial input, the missing part.

    Crops are made on the fly: ``crop="test"`` is the deterministic test protocol (sample
    ``i`` loses the points nearest ``VIEWPOINTS[i % 5]``), ``crop="scanner-test"`` the
    scanner's (sample ``i`` is what ``scanner_test_cameras(S)[i]`` sees, resampled to
    ``N − m``, with ``m`` of the hidden points missing: :mod:`pfnet.data.scanner`); the random
    crops are a function of ``(seed, epoch, index)`` only, so they are reproducible and
    independent of the DataLoader's workers. Call :meth:`set_epoch` before each epoch for
    fresh random crops, or index with ``(epoch, index)`` pairs: workers that live across
    epochs (``persistent_workers=True``) keep the dataset object they started with, so the
    training loop's batch sampler sends the epoch with every index.

    Args:
        root: A dataset folder written by ``pfnet prepare``.
        split: ``"train"``, ``"val"`` or ``"test"``.
        missing_ratio: Share of points removed, ``m = round(r·N)`` (paper: 0.25).
        crop: One of :data:`CROPS` (``turned``: the paper's viewpoint crop from a random side
            of a shape that keeps its heading, see ``_turned_crop``).
        seed: Seed of the random crops.
        fresh_points: With a random crop and a split that has a pool of points
            (``pfnet prepare --pool``): every access draws a new cloud of N points from the
            shape's pool (without replacement, seeded by ``(seed, epoch, index)``) before the
            crop, as the authors' loader draws 2048 of the raw points every time. The test
            protocols always use the stored cloud.
        augment: With a random crop: an :class:`~pfnet.data.augment.Augmentation` applied
            to the complete cloud before the crop (seeded by ``(seed, epoch, index)``).
        frame: ``shape`` (the stored frame, the paper's), ``scan`` (every sample normalised
            by its partial cloud's own centroid and radius), ``aligned`` (then turned about
            the up axis to the partial's main horizontal axis) or ``heading`` (training
            partials in the scan frame, in the data set's own heading; turned test partials
            turned back by the heading the shipped reader reads, :mod:`pfnet.data.heading`);
            see :func:`pfnet.data.scan_frame.scan_frame`.
        up_axis: Index of the data set's up axis: what ``aligned`` turns about, and (with
            the test crop and ``turn_test``) what each sample is first turned about by the
            scan protocol's angle for it. ``None``: no test turn, and y for ``aligned``.
        turn_test: Whether the test crop's samples are turned (in a scan frame).
        views: With a test crop: 1 (the paper's, sample ``i`` at ``VIEWPOINTS[i % 5]``) or
            5: every shape cut at all five viewpoints, as samples ``5 i`` to ``5 i + 4``
            (named ``NAME-vV``; :func:`pfnet.data.crops.every_view`), each in a pose of its
            own under the scan protocol's turn.

    Each item is a dict: ``partial`` ``(N - m, 3)``, ``missing`` ``(m, 3)``, ``complete``
    ``(N, 3)`` (for the scanner crops, the partial and the missing points together) float32
    tensors, ``category`` and ``name`` str, ``index`` int, and
    ``frame_radius`` (float32 scalar tensor): the radius the frame divided by (1 in the
    shape frame), by which distances are multiplied to score in the data set's units.
    """

    def __init__(
        self,
        root: str | os.PathLike[str],
        split: str,
        *,
        missing_ratio: float = 0.25,
        crop: str = "test",
        seed: int = 0,
        fresh_points: bool = False,
        augment: Augmentation | None = None,
        frame: str = "shape",
        up_axis: int | None = None,
        turn_test: bool = True,
        views: int = 1,
    ) -> None:
        if frame not in FRAMES:
            raise ConfigError(f"frame must be one of {', '.join(FRAMES)}, got {frame!r}")
        if up_axis not in (None, 0, 1, 2):
            raise ConfigError(f"up_axis must be 0, 1, 2 or None, got {up_axis!r}")
        self.frame = frame
        self.up_axis = up_axis
        self.turn_test = bool(turn_test)
        if crop not in CROPS:
            raise ConfigError(f"crop must be one of {', '.join(CROPS)}, got {crop!r}")
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ConfigError(f"seed must be a non-negative integer, got {seed!r}")
        if views != 1 and crop not in TEST_CROPS:
            raise ConfigError(
                f"views = {views!r} cuts each shape at several viewpoints of a test crop "
                f"({', '.join(TEST_CROPS)}); a {crop!r} crop draws its own"
            )
        self.clouds: CloudSet = every_view(load_split(root, split), views)
        self.views = views
        self.split = split
        self.crop = crop
        self.seed = seed
        self.missing_ratio = missing_ratio
        self.n_points = self.clouds.n_points
        if self.n_points == 0:  # a KITTI data set stores the cars' scans, no complete cloud
            raise DataError(
                f"{root} holds no complete clouds (a KITTI data set: for predict and evaluate "
                "--protocol kitti only); train on a data set of complete clouds"
            )
        self.n_missing = missing_count(self.n_points, missing_ratio)
        self.epoch = 0
        deterministic = crop in TEST_CROPS
        self.fresh_points = (
            bool(fresh_points) and not deterministic and self.clouds.extra is not None
        )
        self.augment = (
            augment if augment is not None and augment.active and not deterministic else None
        )
        self._viewpoints = test_protocol_viewpoints(len(self.clouds))
        # the scanner's cameras stand above the data set's up axis (y when it is not known)
        self._camera_up = _manifest_up_axis(root) if up_axis is None else up_axis

    def __len__(self) -> int:
        return len(self.clouds)

    @property
    def categories(self) -> list[str]:
        """The split's distinct categories, sorted."""
        return self.clouds.categories

    def set_epoch(self, epoch: int) -> None:
        """Select the random crops of ``epoch`` (a non-negative integer)."""
        if isinstance(epoch, bool) or not isinstance(epoch, int) or epoch < 0:
            raise ConfigError(f"epoch must be a non-negative integer, got {epoch!r}")
        self.epoch = epoch

    def crop_seed(self, index: int, epoch: int | None = None, stream: int = 0) -> int:
        """The seed of sample ``index``'s random crop at ``epoch`` (default: the current one).

        ``stream=1`` gives an independent seed for the draw of its points from the pool.
        """
        epoch = self.epoch if epoch is None else epoch
        key = [self.seed, epoch, index] + ([stream] if stream else [])
        state = np.random.SeedSequence(key).generate_state(2, np.uint32)
        return int(state[0]) << 32 | int(state[1])

    def cloud(self, index: int, epoch: int | None = None) -> np.ndarray:
        """The complete cloud of sample ``index`` at ``epoch``: the stored one, or with
        ``fresh_points`` a new draw of N points from the shape's pool; then augmented."""
        points = self.clouds.points[index]
        if self.fresh_points and self.clouds.extra is not None:
            pool = np.concatenate([points, self.clouds.extra[index]])
            rng = np.random.default_rng(self.crop_seed(index, epoch, stream=1))
            points = pool[np.sort(rng.choice(len(pool), self.n_points, replace=False))]
        if self.augment is not None:
            points = self.augment(points, np.random.default_rng(self.crop_seed(index, epoch, 2)))
        return points

    def __getitem__(self, key: int | tuple[int, int]) -> dict:
        """Sample ``key``: an index (at the current epoch) or an ``(epoch, index)`` pair."""
        epoch = None
        if isinstance(key, tuple):
            if len(key) != 2:
                raise TypeError(f"expected an index or an (epoch, index) pair, got {key!r}")
            epoch, index = operator.index(key[0]), operator.index(key[1])
            if epoch < 0:
                raise ConfigError(f"epoch must be a non-negative integer, got {epoch!r}")
        else:
            index = operator.index(key)
        if not -len(self) <= index < len(self):
            raise IndexError(f"index {index} out of range for a dataset of {len(self)} samples")
        index %= len(self)
        from pfnet.geometry import crop_by_viewpoint, random_crop

        complete = self.cloud(index, epoch)
        if self.crop == "test":
            partial, missing = crop_by_viewpoint(
                complete, self._viewpoints[index], n_missing=self.n_missing
            )
        elif self.crop in ("scanner", "scanner-test"):
            partial, missing = self._scanner_sample(index, epoch, complete)
            complete = np.concatenate([partial, missing])  # N points, as the model's sample
        elif self.crop == "turned":
            partial, missing = self._turned_crop(index, epoch, complete)
        else:
            partial, missing = random_crop(
                complete,
                self.n_missing,
                seed=self.crop_seed(index, epoch),
                n_regions=_MULTI_REGIONS if self.crop == "multi" else 1,
                directions="sphere" if self.crop == "sphere" else "viewpoints",
            )
        radius = 1.0
        if self.frame != "shape":
            partial, missing, complete, radius = self._scan_frame(index, partial, missing, complete)
        return {
            "partial": torch.from_numpy(np.ascontiguousarray(partial)),
            "missing": torch.from_numpy(np.ascontiguousarray(missing)),
            "complete": torch.from_numpy(complete.copy()),
            "category": str(self.clouds.category[index]),
            "name": str(self.clouds.name[index]),
            "index": index,
            "frame_radius": torch.tensor(radius, dtype=torch.float32),
        }

    def _turned_crop(self, index, epoch, cloud):
        """``(partial, missing)`` of the ``turned`` crop: one of the paper's viewpoints, turned
        about the data set's up axis by a random angle (both drawn from ``(seed, epoch,
        index)``). The shape keeps its heading and the cut comes from any side: the
        ``viewpoint`` crop of the shape turned by that angle, turned back (the points are the
        cloud's own, uncut by rounding)."""
        from pfnet.geometry import VIEWPOINTS, crop_by_viewpoint

        rng = np.random.default_rng(self.crop_seed(index, epoch, stream=3))
        view = np.asarray(VIEWPOINTS[int(rng.integers(len(VIEWPOINTS)))], np.float64)
        turned = up_rotation(rng.uniform(0.0, 2.0 * np.pi), self._camera_up) @ view
        return crop_by_viewpoint(cloud, turned.astype(cloud.dtype), n_missing=self.n_missing)

    def _scanner_sample(self, index, epoch, cloud):
        """``(partial, missing)`` of the scanner crops: a random camera drawn from
        ``(seed, epoch, index)``, or the test protocol's camera and resampling of sample
        ``index`` (:func:`pfnet.data.scanner.scanner_test_crop`; independent of the data
        set's seed, as the paper's test crop is)."""
        if self.crop == "scanner-test":
            rng = test_sample_rng(index)
        else:
            rng = np.random.default_rng(self.crop_seed(index, epoch))
        what = f"{self.split} sample {index} ({self.clouds.name[index]})"
        return scanner_sample(
            cloud,
            self.n_points,
            self.n_missing,
            rng,
            up_axis=self._camera_up,
            what=what,
            best_effort=self.crop != "scanner-test",  # a flat shape must not stop a run
        )

    def _scan_frame(self, index, partial, missing, complete):
        """``(partial, missing, complete, radius)`` in the partial's own frame (test crops:
        after the scan protocol's turn about the up axis, unless ``turn_test`` is off)."""
        turned = self.crop in TEST_CROPS and self.turn_test and self.up_axis is not None
        if turned:
            turn = up_rotation(scan_angle(index), self.up_axis).T
            partial, missing, complete = (
                np.asarray(c, np.float64) @ turn for c in (partial, missing, complete)
            )
        up_axis = 1 if self.up_axis is None else self.up_axis
        if self.frame == "heading" and turned:  # read back, as `complete` will read a scan's
            transform = _heading_frame(partial, up_axis, f"{self.split} sample {index}")
        else:  # training partials of the heading frame keep the data set's heading
            transform = frame_of(partial, self.frame, up_axis=up_axis)
        return (
            transform.apply(partial),
            transform.apply(missing),
            transform.apply(complete),
            float(transform.radius),
        )
