"""``pfnet complete``: complete your own partial point clouds with a trained model.

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

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pfnet.devices import DEVICE_HELP
from pfnet.errors import ConfigError, DataError
from pfnet.runtimes import RUNTIME_HELP, RUNTIMES

HELP = "Complete your own partial point clouds (PLY/XYZ/PTS/TXT/NPY/PCD) with a trained model."

PARTIAL_RGB = (154, 154, 154)
PREDICTION_RGB = (242, 194, 0)


@dataclass
class Normalisation:
    """The similarity transform from a cloud's own coordinates to the unit ball.

    Attributes:
        centre: float64 ``(3,)`` subtracted first.
        radius: The largest distance of a point from ``centre``; divided next.
    """

    centre: np.ndarray
    radius: float

    def apply(self, points: np.ndarray) -> np.ndarray:
        """``(N, 3)`` input coordinates -> float32 normalised coordinates."""
        return ((np.asarray(points, np.float64) - self.centre) / self.radius).astype(np.float32)

    def invert(self, points: np.ndarray) -> np.ndarray:
        """``(M, 3)`` normalised coordinates -> float32 input coordinates."""
        return (np.asarray(points, np.float64) * self.radius + self.centre).astype(np.float32)


def normalisation(points: np.ndarray, source: str = "input") -> Normalisation:
    """Centre at the centroid and scale by the max radius, as data preparation does.

    Raises:
        DataError: If all points coincide (no scale to normalise by).
    """
    pts = np.asarray(points, dtype=np.float64)
    centre = pts.mean(axis=0)
    radius = float(np.sqrt(((pts - centre) ** 2).sum(axis=1).max()))
    if not radius > 0.0:
        raise DataError(f"{source}: all {len(pts)} points coincide; nothing to complete")
    return Normalisation(centre=centre, radius=radius)


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
    model: Any, clouds: list[np.ndarray], *, batch_size: int = 32, device: str = "cpu"
) -> list[np.ndarray]:
    """Predict the missing region of each cloud, in the cloud's own coordinates.

    Args:
        model: A completion model in eval mode, with ``n_points`` and ``n_missing`` (or an
            :class:`pfnet.runtimes.OnnxGenerator`).
        clouds: float32 ``(N_i, 3)`` partial clouds in any coordinates, any ``N_i``.
        batch_size: Clouds per forward pass.
        device: Torch device the model lives on.

    Returns:
        One float32 ``(M, 3)`` array per cloud.
    """
    from pfnet.inference import predict_missing

    n_input = int(model.n_points) - int(model.n_missing)
    transforms = [normalisation(c) for c in clouds]
    batch = np.stack(
        [network_input(t.apply(c), n_input) for c, t in zip(clouds, transforms, strict=True)]
    )
    detail = predict_missing(model, batch, batch_size, device)
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


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``pfnet complete``."""
    parser.add_argument(
        "inputs", nargs="+", type=Path, metavar="INPUT", help="partial clouds to complete"
    )
    parser.add_argument(
        "--checkpoint",
        default=None,
        help="checkpoint (best.pt of pfnet train), model file or shipped model's name "
        "(default: the shipped default model; see pfnet models)",
    )
    parser.add_argument("--out", type=Path, required=True, help="folder for the PLY outputs")
    parser.add_argument("--batch-size", type=int, default=32, help="clouds per batch (default: 32)")
    parser.add_argument("--device", default="auto", help=DEVICE_HELP)
    parser.add_argument("--runtime", choices=RUNTIMES, default="auto", help=RUNTIME_HELP)


def run(args: argparse.Namespace) -> int:
    """Run ``pfnet complete``; exit 2 if some inputs could not be read (the rest are done)."""
    from pfnet.io import refuse_input_overwrite
    from pfnet.runtimes import load_generator

    if args.batch_size < 1:
        raise ConfigError(f"--batch-size must be at least 1, got {args.batch_size}")
    stems: dict[str, Path] = {}
    for path in args.inputs:
        # casefold: Scan.npy and scan.npy would write one file on macOS and Windows
        stem = path.stem.casefold()
        if stem in stems and stems[stem] != path:
            raise ConfigError(
                f"inputs {stems[stem]} and {path} would both write "
                f"{path.stem}_completed.ply; rename one or complete them separately"
            )
        stems[stem] = path
    if args.out.exists() and not args.out.is_dir():
        raise ConfigError(f"--out {args.out} is a file; name a folder for the outputs")
    inputs = list(dict.fromkeys(args.inputs))
    # `complete a.ply a_missing.ply --out .` would replace the user's a_missing.ply.
    refuse_input_overwrite(
        [output for path in inputs for output in output_paths(args.out, path)], inputs
    )
    loaded = load_generator(args.checkpoint, runtime=args.runtime, device=args.device)
    model, device = loaded.model, loaded.device
    created = not args.out.exists()
    args.out.mkdir(parents=True, exist_ok=True)
    try:
        done, failed = _complete_all(args, model, inputs, device)
    except KeyboardInterrupt:
        if created and not any(args.out.iterdir()):
            args.out.rmdir()  # an interrupted first batch leaves no empty folder behind
        raise
    print(
        f"completed {done} of {len(inputs)} file(s) into {args.out} "
        f"(<stem>_missing.ply and <stem>_completed.ply)"
    )
    if failed:
        print(f"pfnet complete: {len(failed)} file(s) could not be read", file=sys.stderr)
        return 2
    return 0


def _complete_all(args: argparse.Namespace, model, inputs: list[Path], device: str):
    """Complete ``inputs`` batch by batch; return (files done, messages of files skipped)."""
    from tqdm import tqdm

    from pfnet.io import read_point_cloud

    failed: list[str] = []
    done = 0
    chunk = max(args.batch_size, 1)
    progress = tqdm(total=len(inputs), desc="complete", unit="file", disable=None)
    for start in range(0, len(inputs), chunk):
        paths, clouds = [], []
        for path in inputs[start : start + chunk]:
            try:
                cloud = read_point_cloud(path)
                normalisation(cloud, str(path))  # reject degenerate clouds before batching
            except DataError as err:
                failed.append(str(err))
                print(f"skipped: {err}", file=sys.stderr)
                progress.update(1)
                continue
            paths.append(path)
            clouds.append(cloud)
        if clouds:
            predicted = complete_clouds(model, clouds, batch_size=chunk, device=device)
            for path, cloud, missing in zip(paths, clouds, predicted, strict=True):
                write_completion(args.out, path, cloud, missing)
                done += 1
                progress.update(1)
    progress.close()
    return done, failed
