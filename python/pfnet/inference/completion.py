"""Completing your own partial point clouds with a trained model: :func:`complete` from
Python, ``pfnet complete`` from the shell (the work behind both).

For each partial cloud (an array, or a ``.ply .xyz .pts .txt .npy .pcd`` file, see
:mod:`pfnet.io.clouds`):

1. Turn it to the data sets' y-up frame if its up axis is z (``up="z"``,
   :func:`pfnet.data.scan_frame.to_y_up`).
2. Normalise it in the scan frame (DESIGN.md §3, :mod:`pfnet.data.scan_frame`): subtract its
   own centroid and divide by the largest distance from it (the max radius), in float64, so
   the partial cloud fits the unit ball. A model trained with ``frame = "scan"`` saw its
   training partials so; one trained in the ``shape`` frame (the paper's) did not, and
   completes scans worse (the output says which).
3. Resample *for the network input only* to ``n = n_points - n_missing`` points, the
   partial size the model was trained on: a larger cloud is reduced by iterative farthest
   point sampling (from its first point), a smaller one is repeated cyclically (point
   ``k`` is input point ``k mod N``; duplicates leave the max-pooled features unchanged).
4. Predict the missing region (M points). With a mirror fill (``mirror_fill``, ``pfnet
   complete --mirror-fill``; :data:`DEFAULT_MIRROR_FILL` by default), the predicted points
   near the partial's own mirror images are swapped for those images
   (:func:`pfnet.data.symmetry.mirror_fill`): the network says where the missing piece is, the
   mirror puts points on its surface. Map the points back through steps 2 and 1.
5. ``pfnet complete`` writes ``OUT/<stem>_missing.ply`` (the M predicted points, yellow) and
   ``OUT/<stem>_completed.ply`` (every input point, unchanged and in its original order,
   grey, followed by the predicted points, yellow).

Input points are never moved or dropped: the completed cloud starts with exactly the
coordinates given (or that :func:`pfnet.io.clouds.read_point_cloud` returned, float64 kept where the
file holds float64 or text: the PLY outputs are then written in double).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pfnet.errors import ConfigError, DataError
from pfnet.inference.predict import input_frame, network_input, normalisation
from pfnet.io.palette import PARTIAL_COLOR, PREDICTION_COLOR, rgb

DEFAULT_MIRROR_FILL = 0.15
"""How far (in the scan's normalised units, its radius 1) a mirror image of the partial may be
from the network's prediction and still replace its points; 0 leaves the prediction as it is.
Chosen on SweetHome3D's validation split through the scan protocol (docs/scan-protocol.md):
``sh3d-mirror``'s F-score@0.01 doubles there (0.0157 to 0.0322) for a Chamfer distance 14 %
larger (30.7 to 35.1)."""

# The PLY outputs carry render's colours: the partial input grey, the prediction yellow.
PARTIAL_RGB = rgb(PARTIAL_COLOR)
PREDICTION_RGB = rgb(PREDICTION_COLOR)


def complete_clouds(
    model: Any,
    clouds: list[np.ndarray],
    *,
    up: str = "y",
    frame: str = "scan",
    batch_size: int = 32,
    device: str = "cpu",
    source: Any = "in use",
    mirror_fill: float = 0.0,
) -> list[np.ndarray]:
    """Predict the missing region of each cloud, in the cloud's own coordinates.

    Args:
        model: A completion model in eval mode, with ``n_points`` and ``n_missing`` (or an
            :class:`pfnet.inference.runtimes.OnnxGenerator`).
        clouds: ``(N_i, 3)`` float partial clouds in any coordinates, any ``N_i``.
        up: The clouds' up axis, ``y`` or ``z`` (:data:`pfnet.data.scan_frame.UP_AXES`).
        frame: The model's frame (its config's ``frame``): ``aligned`` turns each cloud to
            its main horizontal axis; ``scan`` and ``shape`` do not (a scan has no shape
            frame: its own centroid and radius are all there is).
        batch_size: Clouds per forward pass.
        device: Torch device the model lives on.
        source: The checkpoint the model came from, named in errors.
        mirror_fill: The reach of :func:`pfnet.data.symmetry.mirror_fill` (0: the network's
            points as they are).

    Returns:
        One ``(M, 3)`` array per cloud: float64 for a float64 cloud (a survey scan's
        coordinates keep their precision), else float32.

    Raises:
        DataError: The model's output is not finite points of the expected shape
            (:func:`pfnet.inference.runtimes.check_detail`).
        ConfigError: ``mirror_fill`` is negative or not finite.
    """
    from pfnet.data.scan_frame import to_y_up
    from pfnet.data.symmetry import mirror_fill as fill
    from pfnet.inference.predict import predict_missing

    check_mirror_fill(mirror_fill)
    turn = to_y_up(up)
    n_input = int(model.n_points) - int(model.n_missing)
    turned = [np.asarray(c, np.float64) @ turn.T for c in clouds]
    transforms = [input_frame(c, frame) for c in turned]
    batch = np.stack(
        [network_input(t.apply(c), n_input) for c, t in zip(turned, transforms, strict=True)]
    )
    detail = predict_missing(model, batch, batch_size, device, source=source)
    out = []
    for cloud, upright, transform, points, seen in zip(
        clouds, turned, transforms, detail, batch, strict=True
    ):
        if mirror_fill > 0:  # the network's input, or the partial itself if smaller (no repeats)
            partial = seen if len(upright) > n_input else transform.apply(upright)
            points = fill(points, partial, reach=mirror_fill, up_axis=1)
        mapped = transform.invert(points) @ turn
        dtype = np.float64 if np.asarray(cloud).dtype == np.float64 else np.float32
        out.append(mapped.astype(dtype))
    return out


@dataclass(frozen=True)
class Completion:
    """What :func:`complete` returns.

    Attributes:
        missing: ``(M, 3)`` the predicted missing region, in the input's coordinates
            (float64 for a float64 input, else float32).
        completed: ``(N + M, 3)`` the input's points, exactly as given and in their order,
            followed by ``missing``.
        model: The model file that completed it.
        frame: The frame that model was trained in (``scan`` or ``shape``, see
            :data:`pfnet.data.scan_frame.FRAMES`).
        runtime: ``torch`` or ``onnx``.
        mirror_fill: The mirror fill's reach (0: the network's points as they are).
    """

    missing: np.ndarray
    completed: np.ndarray
    model: str
    frame: str
    runtime: str
    mirror_fill: float = 0.0

    def __repr__(self) -> str:
        return (
            f"Completion(missing={self.missing.shape[0]} points, completed="
            f"{self.completed.shape[0]} points, model={Path(self.model).name!r}, "
            f"frame={self.frame!r}, runtime={self.runtime!r}, mirror_fill={self.mirror_fill!r})"
        )


_LOADED: dict[tuple[str, str, str], Any] = {}


def load_model(
    model: str | os.PathLike[str] | None = None, *, runtime: str = "auto", device: str = "auto"
) -> Any:
    """Load a completion model once and keep it for later calls (a
    :class:`pfnet.inference.runtimes.LoadedGenerator`).

    Args:
        model: A shipped model's name (see ``pfnet models``), a model file, a ``best.pt``,
            or an ``.onnx`` export; ``None`` for the default shipped model.
        runtime: ``auto`` (PyTorch if installed, else ONNX Runtime), ``torch`` or ``onnx``.
        device: ``auto``, ``cpu``, ``cuda`` or ``cuda:N``.

    Raises:
        ConfigError, DataError, MissingDependency: As ``pfnet complete``'s ``--checkpoint``.
    """
    from pfnet.inference.runtimes import load_generator
    from pfnet.inference.shipped import resolve_checkpoint

    path = resolve_checkpoint(model)
    key = (str(path.resolve()), runtime, device)
    if key not in _LOADED:
        _LOADED[key] = load_generator(path, runtime=runtime, device=device)
    return _LOADED[key]


def complete(
    points: Any,
    model: Any = None,
    *,
    up: str = "y",
    runtime: str = "auto",
    device: str = "auto",
    mirror_fill: float = DEFAULT_MIRROR_FILL,
) -> Completion:
    """Complete one partial point cloud.

    Example::

        import numpy as np, pfnet
        scan = np.loadtxt("scan.xyz")          # (N, 3), z up
        result = pfnet.complete(scan, up="z")
        result.missing                         # (512, 3) predicted points, scan's coordinates

    Args:
        points: ``(N, 3)`` finite coordinates (any float or integer dtype), ``N >= 2``.
        model: A shipped model's name, a model file, checkpoint or ``.onnx`` export, a model
            returned by :func:`load_model`, or ``None`` for the default shipped model.
        up: The cloud's up axis, ``y`` (the default; SweetHome3D, OpenGL) or ``z`` (ROS,
            most scanners and LiDAR).
        runtime: ``auto``, ``torch`` or ``onnx`` (ignored for a model already loaded).
        device: ``auto``, ``cpu``, ``cuda`` or ``cuda:N`` (likewise).
        mirror_fill: How near the partial's mirror images must be to the prediction to
            replace its points (:data:`DEFAULT_MIRROR_FILL`; 0: the network's points only).

    Returns:
        A :class:`Completion`.

    Raises:
        DataError: ``points`` is not an ``(N, 3)`` array of finite numbers, or all its points
            coincide.
        ConfigError: An unknown ``up``, runtime or device, or a negative ``mirror_fill``.
    """
    from pfnet.data.scan_frame import to_y_up
    from pfnet.inference.runtimes import LoadedGenerator

    to_y_up(up)  # ConfigError for a bad axis before a model is loaded
    check_mirror_fill(mirror_fill)
    cloud = check_points(points)
    normalisation(cloud)
    loaded = (
        model
        if isinstance(model, LoadedGenerator)
        else load_model(model, runtime=runtime, device=device)
    )
    frame = getattr(loaded.config, "frame", "shape")
    (missing,) = complete_clouds(
        loaded.model,
        [cloud],
        up=up,
        frame=frame,
        device=loaded.device,
        source=loaded.source,
        mirror_fill=mirror_fill,
    )
    completed = np.concatenate([cloud, missing.astype(cloud.dtype, copy=False)])
    return Completion(missing, completed, str(loaded.source), frame, loaded.runtime, mirror_fill)


def check_mirror_fill(reach: float) -> None:
    """Raise :class:`ConfigError` unless ``reach`` is a finite number ``>= 0``."""
    if not (isinstance(reach, int | float) and np.isfinite(reach) and reach >= 0):
        raise ConfigError(f"mirror fill must be a finite distance >= 0 (0: off), got {reach!r}")


def check_points(points: Any, source: str = "points") -> np.ndarray:
    """``points`` as an ``(N, 3)`` float array (float64 kept, other dtypes as float32).

    Raises:
        DataError: Not ``(N, 3)`` with ``N >= 1``, not numbers, or not finite.
    """
    try:
        array = np.asarray(points)
    except (TypeError, ValueError) as err:
        raise DataError(f"{source}: not an array of points ({err})") from None
    if array.ndim != 2 or array.shape[1] != 3 or array.shape[0] < 1:
        raise DataError(f"{source} must have shape (N, 3) with N >= 1, got {array.shape}")
    if array.dtype.kind not in "fiu":
        raise DataError(f"{source} must hold numbers, got dtype {array.dtype}")
    array = array.astype(np.float64 if array.dtype == np.float64 else np.float32, copy=False)
    if not np.isfinite(array).all():
        raise DataError(f"{source} holds NaN or infinite coordinates")
    return array


def output_paths(out_dir: Path, source: Path) -> tuple[Path, Path]:
    """``(OUT/<stem>_missing.ply, OUT/<stem>_completed.ply)`` for input ``source``."""
    return out_dir / f"{source.stem}_missing.ply", out_dir / f"{source.stem}_completed.ply"


def write_completion(out_dir: Path, source: Path, cloud: np.ndarray, missing: np.ndarray) -> None:
    """Write both PLY files of one input (see the module docstring)."""
    from pfnet.io.clouds import write_ply

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
    from pfnet.io.files import refuse_input_overwrite

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
    """Whether ``path`` is a PLY file as :func:`pfnet.io.clouds.write_ply` writes it (its header's
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
    up: str = "y",
    frame: str = "scan",
    batch_size: int = 32,
    device: str = "cpu",
    on_skip: Callable[[DataError], None] | None = None,
    source: Any = "in use",
    mirror_fill: float = DEFAULT_MIRROR_FILL,
) -> tuple[list[Path], list[str]]:
    """Complete ``inputs`` batch by batch into ``out_dir`` (created if needed).

    A file that cannot be read, or whose points all coincide, is skipped (``on_skip`` is told
    at once) and the rest are completed. A first batch interrupted or refused, or inputs none
    of which could be read, leave no empty folder.
    ``source`` (the checkpoint) is named if the model's output is refused; ``up`` is the
    inputs' up axis and ``frame`` the model's, ``mirror_fill`` the reach of the mirror fill
    (see :func:`complete_clouds`).

    Returns:
        The files written (two per input completed, in input order) and the messages of the
        files skipped.

    Raises:
        ConfigError: If ``batch_size < 1`` or ``mirror_fill`` is negative.
        DataError: The model's output is refused (:func:`pfnet.inference.runtimes.check_detail`);
            the batch it was for is not written.
    """
    if batch_size < 1:
        raise ConfigError(f"batch size must be at least 1, got {batch_size}")
    check_mirror_fill(mirror_fill)
    from pfnet.io.locks import folder_lock

    created = not out_dir.exists()
    out_dir.mkdir(parents=True, exist_ok=True)
    try:
        # one complete at a time in a folder: two once interleaved their files silently
        with folder_lock(out_dir, "writing completions into"):
            done, failed = _complete_batches(
                model,
                inputs,
                out_dir,
                (up, frame, mirror_fill),
                batch_size,
                device,
                on_skip,
                source,
            )
    except (KeyboardInterrupt, DataError):  # Ctrl-C, or a model whose output is refused
        if created and not any(out_dir.iterdir()):
            out_dir.rmdir()
        raise
    if created and not done and not any(out_dir.iterdir()):  # no input could be read
        out_dir.rmdir()
    return done, failed


def _complete_batches(model, inputs, out_dir, pose, batch_size, device, on_skip, source):
    """:func:`complete_files` without the folder's creation and clean-up."""
    from tqdm import tqdm

    from pfnet.io.clouds import read_point_cloud

    failed: list[str] = []
    done: list[Path] = []
    progress = tqdm(total=len(inputs), desc="complete", unit="file", disable=None)
    for start in range(0, len(inputs), batch_size):
        paths, clouds = [], []
        for path in inputs[start : start + batch_size]:
            try:
                cloud = read_point_cloud(path, keep_float64=True)
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
            up, frame, reach = pose
            predicted = complete_clouds(
                model,
                clouds,
                up=up,
                frame=frame,
                batch_size=batch_size,
                device=device,
                source=source,
                mirror_fill=reach,
            )
            for path, cloud, missing in zip(paths, clouds, predicted, strict=True):
                write_completion(out_dir, path, cloud, missing)
                done.extend(output_paths(out_dir, path))
                progress.update(1)
    progress.close()
    return done, failed
