"""Completing your own partial point clouds with a trained model (the work behind
``pfnet complete``).

For each input file (``.ply .xyz .pts .txt .npy .pcd``, see :mod:`pfnet.io`):

1. Normalise as the data sets are prepared (DESIGN.md §3, :func:`pfnet.data.sampling.normalize`):
   subtract the centroid and divide by the largest distance from it (the max radius), so
   the partial cloud fits the unit ball.
2. Resample *for the network input only* to ``n = n_points - n_missing`` points, the
   partial size the model was trained on: a larger cloud is reduced by iterative farthest
   point sampling (from its first point), a smaller one is repeated cyclically (point
   ``k`` is input point ``k mod N``; duplicates leave the max-pooled features unchanged).
3. Predict the missing region (M points) and map it back: ``p · radius + centre``.
4. Write ``OUT/<stem>_missing.ply`` (the M predicted points, yellow) and
   ``OUT/<stem>_completed.ply`` (every input point, unchanged and in its original order,
   grey, followed by the predicted points, yellow).

Input points are never moved or dropped: the completed cloud starts with exactly the
float32 coordinates :func:`pfnet.io.read_point_cloud` returned.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from pfnet.data.sampling import Normalisation, unit_ball
from pfnet.errors import ConfigError, DataError
from pfnet.rendering import PARTIAL_COLOR, PREDICTION_COLOR, rgb

# The PLY outputs carry render's colours: the partial input grey, the prediction yellow.
PARTIAL_RGB = rgb(PARTIAL_COLOR)
PREDICTION_RGB = rgb(PREDICTION_COLOR)


def normalisation(points: np.ndarray, source: str = "input") -> Normalisation:
    """Centre at the centroid and scale by the max radius, as data preparation does.

    Raises:
        DataError: If all points coincide (no scale to normalise by).
    """
    transform = unit_ball(points)
    if transform is None:
        raise DataError(f"{source}: all {len(points)} points coincide; nothing to complete")
    return transform


def network_input(points: np.ndarray, n_input: int) -> np.ndarray:
    """Resample a normalised ``(N, 3)`` cloud to exactly ``n_input`` points.

    More points: iterative farthest point sampling from point 0. Fewer: cyclic repetition.

    Returns:
        float32 ``(n_input, 3)``.
    """
    from pfnet.geometry import farthest_point_sample

    n = len(points)
    if n > n_input:
        index = farthest_point_sample(points, n_input, start_index=0)
    else:
        index = np.arange(n_input) % n
    return np.ascontiguousarray(points[index], dtype=np.float32)


def complete_clouds(
    model: Any,
    clouds: list[np.ndarray],
    *,
    batch_size: int = 32,
    device: str = "cpu",
    source: Any = "in use",
) -> list[np.ndarray]:
    """Predict the missing region of each cloud, in the cloud's own coordinates.

    Args:
        model: A completion model in eval mode, with ``n_points`` and ``n_missing`` (or an
            :class:`pfnet.runtimes.OnnxGenerator`).
        clouds: float32 ``(N_i, 3)`` partial clouds in any coordinates, any ``N_i``.
        batch_size: Clouds per forward pass.
        device: Torch device the model lives on.
        source: The checkpoint the model came from, named in errors.

    Returns:
        One float32 ``(M, 3)`` array per cloud.

    Raises:
        DataError: The model's output is not finite points of the expected shape
            (:func:`pfnet.inference.check_detail`).
    """
    from pfnet.inference import predict_missing

    n_input = int(model.n_points) - int(model.n_missing)
    transforms = [normalisation(c) for c in clouds]
    batch = np.stack(
        [network_input(t.apply(c), n_input) for c, t in zip(clouds, transforms, strict=True)]
    )
    detail = predict_missing(model, batch, batch_size, device, source=source)
    return [t.invert(d) for t, d in zip(transforms, detail, strict=True)]


def output_paths(out_dir: Path, source: Path) -> tuple[Path, Path]:
    """``(OUT/<stem>_missing.ply, OUT/<stem>_completed.ply)`` for input ``source``."""
    return out_dir / f"{source.stem}_missing.ply", out_dir / f"{source.stem}_completed.ply"


def write_completion(out_dir: Path, source: Path, cloud: np.ndarray, missing: np.ndarray) -> None:
    """Write both PLY files of one input (see the module docstring)."""
    from pfnet.io import write_ply

    missing_path, completed_path = output_paths(out_dir, source)
    yellow = np.tile(np.array(PREDICTION_RGB, np.uint8), (len(missing), 1))
    grey = np.tile(np.array(PARTIAL_RGB, np.uint8), (len(cloud), 1))
    write_ply(missing_path, missing, colors=yellow)
    write_ply(
        completed_path, np.concatenate([cloud, missing]), colors=np.concatenate([grey, yellow])
    )


def check_outputs(inputs: list[Path], out_dir: Path, *, overwrite: bool = False) -> list[Path]:
    """The inputs to complete (each once), after checking that their outputs are safe to write.

    An output file that exists is replaced only if pfnet wrote it (:func:`written_by_pfnet`:
    an earlier run's, completed again) or with ``overwrite``: a user's ``scan_completed.ply``
    beside ``scan.xyz`` is never replaced unasked.

    Raises:
        ConfigError: Two inputs would write the same files, ``out_dir`` is a file, an
            output would replace an input, or a file pfnet did not write (without
            ``overwrite``), naming it.
    """
    from pfnet.io import refuse_input_overwrite

    stems: dict[str, Path] = {}
    for path in inputs:
        # casefold: Scan.npy and scan.npy would write one file on macOS and Windows
        stem = path.stem.casefold()
        if stem in stems and stems[stem] != path:
            raise ConfigError(
                f"inputs {stems[stem]} and {path} would both write "
                f"{path.stem}_completed.ply; rename one or complete them separately"
            )
        stems[stem] = path
    if out_dir.exists() and not out_dir.is_dir():
        raise ConfigError(f"output folder {out_dir} is a file; name a folder for the outputs")
    unique = list(dict.fromkeys(inputs))
    # `complete a.ply a_missing.ply --out .` would replace the user's a_missing.ply.
    outputs = [output for path in unique for output in output_paths(out_dir, path)]
    refuse_input_overwrite(outputs, unique)
    for output in outputs:
        if not overwrite and (output.exists() or output.is_symlink()):
            if not written_by_pfnet(output):
                raise ConfigError(
                    f"{output} exists and pfnet did not write it; pass --overwrite to replace "
                    "it, or name another --out"
                )
    return unique


def written_by_pfnet(path: Path) -> bool:
    """Whether ``path`` is a PLY file as :func:`pfnet.io.write_ply` writes it (its header's
    ``comment written by pfnet``), not a link: one that a later run may replace."""
    if path.is_symlink() or not path.is_file():
        return False
    try:
        with open(path, "rb") as fh:
            head = fh.read(128)
    except OSError:
        return False
    return head.startswith(b"ply\nformat binary_little_endian 1.0\ncomment written by pfnet\n")


def complete_files(
    model: Any,
    inputs: list[Path],
    out_dir: Path,
    *,
    batch_size: int = 32,
    device: str = "cpu",
    on_skip: Callable[[DataError], None] | None = None,
    source: Any = "in use",
) -> tuple[int, list[str]]:
    """Complete ``inputs`` batch by batch into ``out_dir`` (created if needed).

    A file that cannot be read, or whose points all coincide, is skipped (``on_skip`` is told
    at once) and the rest are completed. A first batch interrupted or refused, or inputs none
    of which could be read, leave no empty folder.
    ``source`` (the checkpoint) is named if the model's output is refused.

    Returns:
        The number of files completed and the messages of the files skipped.

    Raises:
        ConfigError: If ``batch_size < 1``.
        DataError: The model's output is refused (:func:`pfnet.inference.check_detail`);
            the batch it was for is not written.
    """
    if batch_size < 1:
        raise ConfigError(f"batch size must be at least 1, got {batch_size}")
    from pfnet.locks import folder_lock

    created = not out_dir.exists()
    out_dir.mkdir(parents=True, exist_ok=True)
    try:
        # one complete at a time in a folder: two once interleaved their files silently
        with folder_lock(out_dir, "writing completions into"):
            done, failed = _complete_batches(
                model, inputs, out_dir, batch_size, device, on_skip, source
            )
    except (KeyboardInterrupt, DataError):  # Ctrl-C, or a model whose output is refused
        if created and not any(out_dir.iterdir()):
            out_dir.rmdir()
        raise
    if created and not done and not any(out_dir.iterdir()):  # no input could be read
        out_dir.rmdir()
    return done, failed


def _complete_batches(model, inputs, out_dir, batch_size, device, on_skip, source):
    """:func:`complete_files` without the folder's creation and clean-up."""
    from tqdm import tqdm

    from pfnet.io import read_point_cloud

    failed: list[str] = []
    done = 0
    progress = tqdm(total=len(inputs), desc="complete", unit="file", disable=None)
    for start in range(0, len(inputs), batch_size):
        paths, clouds = [], []
        for path in inputs[start : start + batch_size]:
            try:
                cloud = read_point_cloud(path)
                normalisation(cloud, str(path))  # reject degenerate clouds before batching
            except DataError as err:
                failed.append(str(err))
                if on_skip is not None:
                    on_skip(err)
                progress.update(1)
                continue
            paths.append(path)
            clouds.append(cloud)
        if clouds:
            predicted = complete_clouds(
                model, clouds, batch_size=batch_size, device=device, source=source
            )
            for path, cloud, missing in zip(paths, clouds, predicted, strict=True):
                write_completion(out_dir, path, cloud, missing)
                done += 1
                progress.update(1)
    progress.close()
    return done, failed
