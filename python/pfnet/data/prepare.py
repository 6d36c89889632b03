"""``prepare_dataset``: any source → sampled, normalised clouds in the dataset format.

Shapes are loaded and sampled in parallel worker processes; each shape's random stream
depends only on the seed and its key, and the output is sorted by category and name, so the
same source and seed give byte-identical arrays whatever the number of workers.
"""

from __future__ import annotations

import contextlib
import math
import numbers
import os
import sys
import time
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pfnet.data.distinct import distinct_sample, split_distinct
from pfnet.data.format import (
    FORMAT_NAME,
    FORMAT_VERSION,
    SPLITS,
    CloudSet,
    check_output,
    skipped_entries,
    write_dataset,
)
from pfnet.data.prepared import PrepareReport
from pfnet.data.sampling import normalize, resample_points, sample_surface, shape_rng
from pfnet.data.sources import Scan, ShapeItem
from pfnet.data.sources.merge import merge_scans, several_manifest, several_sources
from pfnet.data.sources.registry import FORMATS, OPEN_SHAPE_FORMATS, load_item
from pfnet.data.splits import assign_splits
from pfnet.errors import ConfigError, DataError
from pfnet.io.files import refuse_overlap
from pfnet.processes import usable_cpus, worker_pool

__all__ = ["assign_splits", "prepare_dataset", "process_item"]


MIN_POINTS = 16
MAX_POINTS = 1 << 16  # the most points a model takes (pfnet.models.config.MAX_POINTS)
# Procedural shapes per category: 10^9 grew past 3 GB before a shape was made.
MAX_COUNT = 100_000
MAX_POOL = 1 << 20  # points per shape; 12 MiB a shape in float32
DEFAULT_PROCEDURAL_COUNT = 100
# Below this many shapes per worker a process pool costs more than it saves.
_MIN_ITEMS_PER_WORKER = 8


def process_item(task: tuple) -> tuple:
    """Load, sample and normalise one shape (runs in a worker process).

    Args:
        task: ``(index, item, n_points, seed[, pool[, distinct]])``.

    Returns:
        ``(index, points float32 (max(n_points, pool), 3), "")`` (the first ``n_points`` are
        the shape's cloud, the rest its pool of extra points, drawn after it from the same
        stream and normalised with the cloud's centroid and radius), or
        ``(index, None, reason)`` on failure. With ``distinct``, two more entries: the
        geometry's digest and its self-distance (:mod:`pfnet.data.distinct`).
    """
    index, item, n_points, seed = task[:4]
    pool = task[4] if len(task) > 4 else 0
    distinct = bool(task[5]) if len(task) > 5 else False
    try:
        geometry = load_item(item, seed)
        rng = shape_rng(seed, item.key)
        if geometry.faces is None:
            points = resample_points(geometry.vertices, n_points, rng, pool)
        else:
            points = sample_surface(geometry.vertices, geometry.faces, n_points, rng)
            if pool > n_points:
                more = sample_surface(geometry.vertices, geometry.faces, pool - n_points, rng)
                points = np.concatenate([points, more])
        if not distinct:
            return index, normalize(points, n_points), ""
        return (index, *distinct_sample(geometry, item, points, n_points, seed))
    except DataError as err:
        return index, None, str(err).removeprefix(f"{item.path}: ")
    except Exception as err:  # a broken file can make any reader fail in its own way
        return index, None, f"cannot read: {type(err).__name__}: {err}"


# More processes than this only add start-up time and memory (each holds a mesh loader).
MAX_WORKERS = 256


def _run(tasks: list, workers: int, progress: bool | None, stop_on_failure: bool) -> list:
    """Process the tasks, in a pool when worth it; results in task order."""
    from tqdm import tqdm

    results = []
    failures = 0
    bar = tqdm(
        total=len(tasks),
        desc="prepare",
        unit="shape",
        file=sys.stderr,
        disable=progress is False or (progress is None and not sys.stderr.isatty()),
    )
    with bar:
        # more processes than a few shapes each only cost start-up time and memory (128
        # workers on 70 meshes took 37 s and 3 GB where 2 took 1.4 s)
        # and more than twice the usable cores only wait for each other (40 workers on 320
        # tiny meshes took 27 s and 2.8 GB on 2 cores, 2 workers 3.3 s)
        workers = min(workers, max(1, len(tasks) // _MIN_ITEMS_PER_WORKER), 2 * usable_cpus())
        with contextlib.ExitStack() as stack:
            if workers <= 1 or len(tasks) < _MIN_ITEMS_PER_WORKER * 2:
                outcomes = map(process_item, tasks)
            else:
                # forkserver: fork() from a multi-threaded parent (torch, the Rust core's
                # thread pool) can deadlock, and Python 3.12+ warns about it; the workers
                # leave Ctrl-C to this process (pfnet.processes)
                pool = stack.enter_context(worker_pool(workers, ["pfnet.data.prepare"]))
                outcomes = pool.imap_unordered(process_item, tasks, chunksize=2)
            for outcome in outcomes:
                results.append(outcome)
                failures += outcome[1] is None
                bar.update(1)
                if failures:
                    bar.set_postfix(failed=failures, refresh=False)
                    if stop_on_failure:
                        break
    return sorted(results, key=lambda r: r[0])


def _is_integer(value: object) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _check_arguments(
    points: int, seed: int, test_fraction: float, val_fraction: float, workers: int | None
) -> None:
    if not _is_integer(points) or not MIN_POINTS <= points <= MAX_POINTS:
        raise ConfigError(
            f"points must be an integer in [{MIN_POINTS}, {MAX_POINTS}] (the most a model "
            f"takes), got {points!r}"
        )
    if not _is_integer(seed) or not 0 <= seed < 2**63:  # as training's seeds: a data set's
        # seed is the demo's and the study's training seed too
        raise ConfigError(f"seed must be an integer in [0, 2**63), got {str(seed)[:40]}")
    for label, value in (("test_fraction", test_fraction), ("val_fraction", val_fraction)):
        if not (isinstance(value, (int, float)) and math.isfinite(value) and 0 <= value < 1):
            raise ConfigError(f"{label} must be in [0, 1), got {value!r}")
    if test_fraction + val_fraction >= 1:
        raise ConfigError(
            f"test_fraction + val_fraction must be below 1 (some shapes must train), got "
            f"{test_fraction} + {val_fraction}"
        )
    if workers is not None and (not _is_integer(workers) or not 1 <= workers <= MAX_WORKERS):
        raise ConfigError(f"workers must be an integer in [1, {MAX_WORKERS}], got {workers!r}")


def _scan(fmt: str, source, count: int | None, strict: bool) -> Scan:
    from pfnet.data.sources import meshes, procedural, shapenet_part, sweethome3d
    from pfnet.data.sources.registry import scan_open_shapes

    if fmt == "procedural":
        if source is not None and str(source) != "procedural":
            raise ConfigError(
                f"the procedural format takes the source 'procedural', got {source!r}"
            )
        return procedural.scan(DEFAULT_PROCEDURAL_COUNT if count is None else count)
    if count is not None:
        raise ConfigError(f"count applies only to the procedural format, not to {fmt}")
    path = Path(source)
    if not path.exists():
        raise DataError(f"{path}: no such file or folder")
    if fmt == "sweethome3d":
        return sweethome3d.scan(path, strict=strict)
    if fmt in OPEN_SHAPE_FORMATS:  # FlightGear, TORCS, crrcsim, SweetHome3D's jar
        return scan_open_shapes(fmt, path)
    if not path.is_dir():
        raise DataError(f"{path}: the {fmt} format needs a folder")
    if fmt == "shapenet-part":
        return shapenet_part.scan(path)
    return meshes.scan(path)


def _select(scan: Scan, fmt: str, categories: Sequence[str] | str | None) -> list[ShapeItem]:
    """The items of the wanted categories; by default SweetHome3D leaves out ``other``."""
    from pfnet.data.sources.sweethome3d import OTHER

    available = sorted({item.category for item in scan.items})
    if isinstance(categories, str):
        categories = [c.strip() for c in categories.split(",") if c.strip()]
    if categories is not None and len(categories) == 0:
        raise ConfigError("categories is empty")
    if categories is None or list(categories) == ["all"]:
        keep = set(available)
        if categories is None and fmt in ("sweethome3d", "sweethome3d-app"):
            keep.discard(OTHER)
            scan.dropped["unmatched"] = sum(item.category == OTHER for item in scan.items)
    else:
        keep = {c.lower() for c in categories}
        unknown = sorted(keep - set(available))
        if unknown:
            raise ConfigError(
                f"categories: {', '.join(unknown)} not in the source; "
                f"available: {', '.join(available)}"
            )
    return [item for item in scan.items if item.category in keep]


def prepare_dataset(
    source: str | os.PathLike[str] | Sequence[str | os.PathLike[str]] | None,
    out: str | os.PathLike[str],
    *,
    format: str = "auto",
    points: int | None = None,
    seed: int = 0,
    test_fraction: float = 0.2,
    val_fraction: float = 0.1,
    categories: Sequence[str] | str | None = None,
    workers: int | None = None,
    count: int | None = None,
    pool: int | None = None,
    strict: bool = False,
    overwrite: bool = False,
    progress: bool | None = None,
    distinct: bool | None = None,
) -> PrepareReport:
    """Build a completion dataset (DESIGN.md §3) from meshes, point clouds or procedural shapes.

    Every shape: ``points`` points sampled uniformly (area-weighted, seeded) on its surface,
    or a point cloud resampled to ``points`` (IFPS when it has more, seeded copies when it
    has fewer); then centred at the centroid and divided by the max radius (paper §4.1).

    Args:
        source: A folder or ``.sh3f`` file; ``None`` or ``"procedural"`` for procedural shapes;
            or a list of mesh and catalogue sources, prepared into one data set
            (:func:`pfnet.data.sources.merge.merge_scans`).
        out: The dataset folder to write (atomically).
        format: ``"auto"`` or one of ``meshes``, ``shapenet-part``, ``sweethome3d``,
            ``procedural``, or a benchmark layout (``pcn``, ``shapenet-55``, ``shapenet-34``,
            ``shapenet-unseen21``; :mod:`pfnet.data.benchmarks`), which keeps the
            benchmark's own clouds, splits and coordinates.
        points: Points per shape (default 2048; benchmarks keep their own count).
        seed: Seeds sampling, procedural shapes and splits.
        test_fraction: Share of each category for ``test`` (sources without their own split).
        val_fraction: Share of each category for ``val`` (sources without their own split).
        categories: Categories to keep (a list or a comma-separated string); ``"all"`` keeps
            everything, including SweetHome3D's unmatched ``other`` models.
        workers: Worker processes (default: the usable CPU cores).
        count: Shapes per category for the procedural format (default 100).
        pool: Also store this many points per shape in all (``> points``): the shape's
            cloud followed by more points of the same surface, from which training draws a
            fresh cloud on every access. The clouds themselves are unchanged by it.
        strict: Fail on the first unreadable or degenerate file instead of skipping it.
        overwrite: Replace an existing, non-empty ``out``.
        progress: Show a progress bar on stderr (default: when stderr is a terminal).
        distinct: Identical geometry once, near-copies in one split (:mod:`pfnet.data.distinct`).

    Returns:
        The report: counts per split and category, skipped files, timing.

    Raises:
        ConfigError: An argument is out of range.
        DataError: The source is missing, empty or of unknown format; every shape failed; or
            (with ``strict``) any shape failed.
    """
    from pfnet.data.benchmarks import BENCHMARK_FORMATS, prepare_benchmark

    start = time.perf_counter()
    if format != "auto" and format not in (*FORMATS, *BENCHMARK_FORMATS):
        raise ConfigError(
            f"format must be auto or one of {', '.join((*FORMATS, *BENCHMARK_FORMATS))}, "
            f"got {format!r}"
        )
    source, sources, formats, fmt = several_sources(source, format, BENCHMARK_FORMATS)
    procedural = sources is None and (source is None or str(source) == "procedural")
    if fmt != "procedural" and procedural:
        raise ConfigError(f"the {fmt} format needs a source path")
    if fmt in BENCHMARK_FORMATS:
        if points is not None or pool is not None or count is not None:
            raise ConfigError(
                f"the {fmt} benchmark keeps its own clouds: points, pool and count do not apply"
            )
        _check_arguments(2048, seed, test_fraction, val_fraction, workers)
        refuse_overlap(out, [source], flag="data set folder")
        check_output(out, overwrite)
        if isinstance(categories, str):
            categories = [c.strip() for c in categories.split(",") if c.strip()]
        return prepare_benchmark(
            source,
            out,
            fmt,
            categories=None if categories in (None, ["all"]) else list(categories),
            workers=workers,
            strict=strict,
            overwrite=overwrite,
        )
    points = 2048 if points is None else points
    _check_arguments(points, seed, test_fraction, val_fraction, workers)
    points, seed = int(points), int(seed)
    workers = None if workers is None else int(workers)
    if count is not None and (not _is_integer(count) or not 1 <= count <= MAX_COUNT):
        raise ConfigError(f"count must be an integer in [1, {MAX_COUNT}], got {count!r}")
    count = None if count is None else int(count)
    if pool is not None and (not _is_integer(pool) or pool <= points or pool > MAX_POOL):
        raise ConfigError(
            f"pool must be an integer above points ({points}) and at most {MAX_POOL}, got {pool!r}"
        )
    pool = 0 if pool is None else int(pool)
    distinct = sources is not None if distinct is None else bool(distinct)
    if not procedural:
        refuse_overlap(out, sources or [source], flag="data set folder")
    out_path = check_output(out, overwrite)
    scan, origins = (
        merge_scans([(f, s, _scan(f, s, count, strict)) for f, s in zip(formats, sources)])
        if sources
        else (_scan(fmt, source, count, strict), {})
    )
    if strict and scan.skipped:
        path, reason = scan.skipped[0]
        raise DataError(f"{path}: {reason}")
    items = _select(scan, "sweethome3d" if sources is not None else fmt, categories)
    if not items:
        raise DataError(f"{source}: no shapes to prepare")
    splits = (
        [item.split or "train" for item in items]
        if scan.has_splits
        else assign_splits(items, seed, test_fraction, val_fraction)
    )
    tasks = [(index, item, points, seed, pool, distinct) for index, item in enumerate(items)]
    results = _run(tasks, workers or usable_cpus(), progress, stop_on_failure=strict)
    skipped = list(scan.skipped)
    kept: dict[str, list[tuple[ShapeItem, np.ndarray]]] = {split: [] for split in SPLITS}
    loaded = []
    for index, cloud, reason, *extra in results:
        item = items[index]
        if cloud is None:
            if strict:
                raise DataError(f"{item.path}: {reason}")
            skipped.append((item.path, reason))
        else:  # with distinct, the digest and self-distance come too (extra)
            (loaded if distinct else kept[splits[index]]).append((item, cloud, *extra))
    kept, distinct_info = split_distinct(
        loaded, kept, scan.has_splits, seed, test_fraction, val_fraction, origins
    )
    if not any(kept.values()):
        raise DataError(f"{source}: every shape failed ({skipped[0][0]}: {skipped[0][1]})")
    cloud_sets = {split: _cloud_set(kept[split], points, pool) for split in SPLITS}
    counts = {
        split: dict(sorted(Counter(cloud_sets[split].category.tolist()).items()))
        for split in SPLITS
    }
    licenses, credits = _credits(scan, [item for shapes in kept.values() for item, _ in shapes])
    manifest = _manifest(
        fmt, source, points, seed, test_fraction, val_fraction, scan, counts, skipped
    )
    if pool:
        manifest["pool"] = pool
    manifest["licenses"] = licenses
    if credits:
        manifest["credits"] = credits
    several_manifest(manifest, formats or [fmt], sources, distinct_info, origins, kept)
    write_dataset(out_path, cloud_sets, manifest, overwrite=overwrite)
    return PrepareReport(
        out=out_path,
        format=fmt,
        counts=counts,
        skipped=skipped,
        dropped={k: v for k, v in scan.dropped.items() if v},
        seconds=time.perf_counter() - start,
        manifest=manifest,
        distinct=distinct_info,
    )


def _cloud_set(
    shapes: list[tuple[ShapeItem, np.ndarray]], n_points: int, pool: int = 0
) -> CloudSet:
    if not shapes:
        return CloudSet.empty(n_points, pool)
    shapes = sorted(shapes, key=lambda s: (s[0].category, s[0].name))
    clouds = np.stack([cloud for _, cloud in shapes])
    return CloudSet(
        np.ascontiguousarray(clouds[:, :n_points]),
        np.array([item.category for item, _ in shapes], dtype=str),
        np.array([item.name for item, _ in shapes], dtype=str),
        np.ascontiguousarray(clouds[:, n_points:]) if pool else None,
    )


def _credits(scan: Scan, kept: list[ShapeItem]) -> tuple[list[dict], dict[str, str]]:
    """The licence records of the sources that contributed shapes (with their model count and
    creators), and ``{name: creator}`` for sources that credit each model."""
    if not scan.credits:
        return scan.licenses, {}
    used: dict[str, list[ShapeItem]] = {}
    for item in kept:
        used.setdefault(scan.credits[item.key][0], []).append(item)
    licenses = []
    for record in scan.licenses:
        items = used.get(record["source"], [])
        if items:
            creators = sorted({scan.credits[i.key][1] for i in items} - {""})
            licenses.append({**record, "models": len(items), "creators": creators})
    credits = {item.name: scan.credits[item.key][1] for item in sorted(kept, key=lambda i: i.name)}
    return licenses, credits


def _manifest(
    fmt, source, points, seed, test_fraction, val_fraction, scan, counts, skipped
) -> dict:
    from pfnet import __version__

    return {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "pfnet_version": __version__,
        "source": {"format": fmt, "path": None if source is None else str(source)},
        "points": points,
        "seed": seed,
        "split": (
            "from the source"
            if scan.has_splits
            else {"test_fraction": test_fraction, "val_fraction": val_fraction, "per": "category"}
        ),
        "normalization": "centroid (mean of the points) at the origin, divided by the max radius",
        "up_axis": "y" if fmt in ("sweethome3d", "procedural") else "as in the source",
        "categories": sorted({c for split in counts.values() for c in split}),
        "splits": {
            split: {"total": sum(counts[split].values()), "categories": counts[split]}
            for split in SPLITS
        },
        "licenses": scan.licenses,
        "dropped": {k: v for k, v in scan.dropped.items() if v},
        **skipped_entries(skipped),
    }
