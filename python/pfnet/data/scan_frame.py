"""The scan protocol (DESIGN.md §3): the frame ``pfnet complete`` gives a network, and the
deterministic poses of the test scans it is measured on.

A real scan has no complete shape to take a centre and a radius from, so ``complete``
normalises each partial cloud by its *own* centroid and max radius, under a rotation about
the up axis nobody knows. A model is trained for that frame with ``frame = "scan"``: every
training partial (cropped from a shape turned by a random angle about the up axis) is
normalised by its own centroid and radius, and its missing region by the same transform.

The protocol's test scans are the paper protocol's partials (sample *i* loses the points
nearest ``VIEWPOINTS[i % 5]``), each put in a pose of its own — turned about the up axis by a
random angle, scaled by a random factor and moved by a random offset, all drawn from
:func:`scan_pose` — and, for z-up scanners, stood z-up. The completion is mapped back through
the pose and scored against the removed points in the data set's frame, so its figures are
those of the paper's protocol when a model is insensitive to where the scan came from.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pfnet.data.sampling import Normalisation, unit_ball
from pfnet.errors import ConfigError

__all__ = [
    "FRAMES",
    "UP_AXES",
    "Pose",
    "ScanFrame",
    "rim_frame",
    "scan_angle",
    "scan_frame",
    "scan_normalisation",
    "scan_pose",
    "to_y_up",
    "up_rotation",
]

# The frame a network's input is given in (DESIGN.md §3, ``ModelConfig.frame``): ``shape``,
# the complete shape's centroid and radius (the paper's protocol: information a real scan
# never has); ``scan``, the partial cloud's own centroid and radius, as ``pfnet complete``
# normalises a scan; or ``aligned``, the scan frame turned about the up axis to the partial's
# main horizontal axis (:func:`scan_frame`); or ``heading``, the scan frame turned back by the
# heading a heading reader reads from the partial (:mod:`pfnet.data.heading`), for a network
# trained on partials in the data set's own heading; ``aligned-end``, ``aligned`` pointing to
# the sparser end of the main axis instead (:data:`END_SHARE`), where a cut end usually is;
# ``aligned-rim``, ``aligned`` given the quarter turn that brings the cut's rim nearest +x
# (:mod:`pfnet.data.rim`); ``rim``, the scan frame turned so that the rim lies at +x.
FRAMES = ("shape", "scan", "aligned", "heading", "aligned-end", "aligned-rim", "rim")

ALIGNED_FRAMES: dict[str, str] = {"aligned": "moment", "aligned-end": "end", "aligned-rim": "rim"}
"""The aligned frames and the sign rule of each one's main axis (:func:`scan_frame`)."""

END_SHARE = 0.15
"""The outer share of the main axis's extent whose points the ``end`` rule counts."""

UP_AXES = ("y", "z")
"""The up axes a scan may have: ``y`` (the data sets', SweetHome3D's, OpenGL's) or ``z``
(ROS, most scanners and LiDAR)."""

# z-up to y-up: (x, y, z) -> (x, z, -y), a proper rotation (determinant +1) taking z to y.
_Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def to_y_up(up: str) -> np.ndarray:
    """The rotation ``(3, 3)`` taking a scan whose up axis is ``up`` to the y-up frame.

    Raises:
        ConfigError: ``up`` is not one of :data:`UP_AXES`.
    """
    if up not in UP_AXES:
        raise ConfigError(f"up axis must be one of {', '.join(UP_AXES)}, got {up!r}")
    return np.eye(3) if up == "y" else _Z_UP_TO_Y_UP.copy()


def up_rotation(angle: float, up_axis: int = 1) -> np.ndarray:
    """The ``(3, 3)`` rotation by ``angle`` radians about coordinate axis ``up_axis``
    (counter-clockwise seen from its positive end; the same as
    :class:`pfnet.data.augment.Augmentation`'s)."""
    a, b = (axis for axis in range(3) if axis != up_axis)
    rotation = np.eye(3)
    cos, sin = np.cos(angle), np.sin(angle)
    rotation[a, a], rotation[a, b] = cos, -sin
    rotation[b, a], rotation[b, b] = sin, cos
    return rotation


@dataclass(frozen=True)
class Pose:
    """A similarity transform ``x -> scale · R x + shift`` (row vectors: ``x @ R.T``).

    Attributes:
        rotation: ``(3, 3)`` proper rotation.
        scale: Positive factor.
        shift: ``(3,)`` offset added last.
    """

    rotation: np.ndarray
    scale: float
    shift: np.ndarray

    def apply(self, points: np.ndarray) -> np.ndarray:
        """``(N, 3)`` points in the pose, float64."""
        return self.scale * (np.asarray(points, np.float64) @ self.rotation.T) + self.shift

    def invert(self, points: np.ndarray) -> np.ndarray:
        """``(N, 3)`` points mapped back from the pose, float64."""
        return ((np.asarray(points, np.float64) - self.shift) / self.scale) @ self.rotation


def scan_pose(index: int, *, up: str = "y", seed: int = 0, turn: bool = True) -> Pose:
    """The pose of test scan ``index`` of the scan protocol.

    A uniform angle about the data set's (y) up axis (none with ``turn=False``), a
    log-uniform scale in [0.1, 10] and an offset of up to 10 of those units per coordinate,
    drawn from ``(seed, index)``; then, for ``up="z"``, the turn that stands the y-up scan
    z-up.
    """
    rng = _pose_rng(index, seed)
    # without the turn the draw is still made, so that the scale and offset stay the same
    angle = rng.uniform(0.0, 2.0 * np.pi) if turn else rng.uniform(0.0, 0.0)
    scale = float(10.0 ** rng.uniform(-1.0, 1.0))
    shift = rng.uniform(-10.0, 10.0, size=3) * scale
    rotation = to_y_up(up).T @ up_rotation(angle, 1)
    return Pose(rotation=rotation, scale=scale, shift=shift)


def _pose_rng(index: int, seed: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([seed, index, 0x5CA7]))


def scan_angle(index: int, *, seed: int = 0) -> float:
    """The angle about the up axis of test scan ``index`` (that of :func:`scan_pose`)."""
    return float(_pose_rng(index, seed).uniform(0.0, 2.0 * np.pi))


def scan_normalisation(partial: np.ndarray) -> Normalisation:
    """The scan frame of one partial cloud: its own centroid and max radius (the identity
    for a cloud whose points all coincide, which has no radius to divide by)."""
    transform = unit_ball(partial)
    if transform is None:
        return Normalisation(centre=np.zeros(3), radius=1.0)
    return transform


@dataclass(frozen=True)
class ScanFrame:
    """The scan frame, optionally turned about the up axis: ``x -> ((x - centre) / radius) R^T``.

    Attributes:
        centre: float64 ``(3,)``, the partial's centroid.
        radius: Its largest distance from the centroid.
        rotation: ``(3, 3)`` turn about the up axis (the identity in the plain scan frame).
    """

    centre: np.ndarray
    radius: float
    rotation: np.ndarray

    def apply(self, points: np.ndarray) -> np.ndarray:
        """``(N, 3)`` coordinates -> float32 coordinates in the frame."""
        normalised = (np.asarray(points, np.float64) - self.centre) / self.radius
        return (normalised @ self.rotation.T).astype(np.float32)

    def invert(self, points: np.ndarray) -> np.ndarray:
        """``(M, 3)`` coordinates in the frame -> float64 input coordinates."""
        return (np.asarray(points, np.float64) @ self.rotation) * self.radius + self.centre


def frame_of(partial: np.ndarray, frame: str, *, up_axis: int = 1) -> ScanFrame:
    """:func:`scan_frame` of ``partial`` for a network trained in ``frame`` (``scan``, ``rim``
    or one of :data:`ALIGNED_FRAMES`; ``heading`` needs a reader, ``shape`` the complete
    shape)."""
    if frame == "rim":
        return rim_frame(partial, up_axis=up_axis)
    sign = ALIGNED_FRAMES.get(frame)
    return scan_frame(partial, aligned=sign is not None, up_axis=up_axis, sign=sign or "moment")


def scan_frame(
    partial: np.ndarray,
    *,
    aligned: bool = False,
    up_axis: int = 1,
    heading: float | None = None,
    sign: str = "moment",
) -> ScanFrame:
    """The frame a scan-frame network sees ``partial`` in (:data:`FRAMES`).

    ``scan``: the partial's own centroid and max radius. ``aligned`` (``aligned=True``): then
    turned about the up axis so that the main axis of its horizontal spread (the principal
    component of the two horizontal coordinates) lies along the first horizontal axis,
    pointing to the side its points reach further (positive third moment). A scan's heading is
    unknown; this turn is a function of the partial alone, so a network trained in it sees its
    training partials as ``complete`` will show it a scan, with far less of the heading left to
    guess (an elongated bed or car up to a half turn, a round table not at all).
    ``sign="end"`` (the ``aligned-end`` frame) points the main axis to its sparser end instead:
    the end with fewer points in the outer :data:`END_SHARE` of the extent (the third moment
    breaks a tie). A cut end keeps fewer points: on SweetHome3D's test cuts whose hole lies
    along the main axis it puts the hole on +x in 95 % of them, the third moment in 81 %
    (``benchmarks/aligned_sign.py``).
    ``sign="rim"`` (the ``aligned-rim`` frame) takes, of the four directions of the main axis
    and its perpendicular, the one nearest the direction of the cut's rim: the centroid of the
    tenth of the points with the highest edge scores (:func:`pfnet.data.rim.rim_centroid`),
    where a point's neighbours lie on one side only. The shape stays turned to its main axis
    (up to a quarter turn) and the hole lies on +x in 84–87 % of SweetHome3D's cuts, the
    horizontal direction of its centroid at a median cosine of 0.99 with +x (the third moment
    and the sparser end: 62–73 %, 0.06–0.15; ``benchmarks/frame_hole.py``).

    ``heading`` (radians, not with ``aligned``): the scan frame turned back by that heading,
    the turn about the up axis that took the data set's frame to the partial's (a heading
    reader's estimate, :mod:`pfnet.data.heading`).
    """
    base = scan_normalisation(partial)
    rotation = np.eye(3)
    if heading is not None:
        if aligned:
            raise ConfigError("scan_frame: give aligned or heading, not both")
        rotation = up_rotation(-float(heading), up_axis)
    if aligned:
        a, b = (axis for axis in range(3) if axis != up_axis)
        flat = ((np.asarray(partial, np.float64) - base.centre) / base.radius)[:, [a, b]]
        values, vectors = np.linalg.eigh(np.cov(flat.T) if len(flat) > 1 else np.eye(2))
        main = vectors[:, int(np.argmax(values))]
        if float(np.mean((flat @ main) ** 3)) < 0:
            main = -main
        if sign == "end":
            x = flat @ main
            reach = END_SHARE * float(x.max() - x.min())
            if int((x > x.max() - reach).sum()) > int((x < x.min() + reach).sum()):
                main = -main
        elif sign == "rim":
            rim = _rim_direction(partial, base, a, b)
            if rim is not None:
                turns = [main, np.array([-main[1], main[0]]), -main, np.array([main[1], -main[0]])]
                main = turns[int(np.argmax([float(t @ rim) for t in turns]))]
        elif sign != "moment":
            raise ConfigError(f"scan_frame: sign must be moment, end or rim, got {sign!r}")
        # the turn about the up axis that takes `main` to the first horizontal axis
        rotation = up_rotation(-float(np.arctan2(main[1], main[0])), up_axis)
    return ScanFrame(centre=base.centre, radius=float(base.radius), rotation=rotation)


def _rim_direction(partial: np.ndarray, base: Normalisation, a: int, b: int) -> np.ndarray | None:
    """The horizontal ``(2,)`` direction (coordinates ``a``, ``b``) from the partial's centroid
    to its rim's (:func:`pfnet.data.rim.rim_centroid`), or None where they coincide."""
    from pfnet.data.rim import rim_centroid

    rim = ((rim_centroid(partial) - base.centre) / base.radius)[[a, b]]
    length = float(np.hypot(rim[0], rim[1]))
    return rim / length if length > 1e-9 else None


def rim_frame(partial: np.ndarray, *, up_axis: int = 1) -> ScanFrame:
    """The ``rim`` frame of ``partial``: its scan frame turned about the up axis so that the
    horizontal direction from its centroid to the cut's rim lies along +x (the first
    horizontal axis). On SweetHome3D's five-view cuts the hole then lies on +x in 89–91 % of
    them, the horizontal direction of its centroid at a median cosine of 0.94–0.95 with +x;
    the shape's own heading is left to the network. A partial whose rim centroid is its
    centroid gets the ``aligned`` frame."""
    base = scan_normalisation(partial)
    a, b = (axis for axis in range(3) if axis != up_axis)
    rim = _rim_direction(partial, base, a, b)
    if rim is None:
        return scan_frame(partial, aligned=True, up_axis=up_axis)
    rotation = up_rotation(-float(np.arctan2(rim[1], rim[0])), up_axis)
    return ScanFrame(centre=base.centre, radius=float(base.radius), rotation=rotation)
