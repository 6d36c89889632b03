"""What defines a completion network and its protocol: :class:`ModelConfig`.

A checkpoint or shipped model stores a training configuration; loading it for inference
reads only these keys, so inference never imports the training package. Does not import
torch. The checks here are shared with ``TrainConfig``, which extends this class with the
training run's settings.
"""

from __future__ import annotations

import dataclasses
import math
import reprlib
from dataclasses import dataclass
from typing import Any, Self

from pfnet.data.scan_frame import FRAMES
from pfnet.errors import ConfigError
from pfnet.models.registry import MODEL_NAMES

# The largest cloud a network may be built for: the paper's 2,048 points with room to spare,
# and a bound a forged checkpoint config cannot get past (n_points = 10**12 made building
# the model fail with a RuntimeError traceback).
MAX_POINTS = 1 << 16

# How a new network's weights start (:func:`pfnet.models.initialise`): PyTorch's per-layer
# defaults, or the authors' N(0, 0.02) convolutions and N(1, 0.02) BatchNorm weights.
INIT_SCHEMES = ("pytorch", "authors")


@dataclass(frozen=True)
class ModelConfig:
    """The network and the protocol it was trained for; enough to rebuild it.

    Attributes:
        model: Generator name, one of :data:`pfnet.models.MODEL_NAMES`.
        n_points: N, points per complete cloud; ``None`` = taken from the dataset.
        missing_ratio: Fraction of the N points removed by the crop; M = round(ratio · N).
        width: Multiplier of every hidden layer (1.0 = the paper's network).
        frame: The frame of the network's input, one of
            :data:`pfnet.data.scan_frame.FRAMES`: ``shape`` (the complete shape's, the paper's;
            what every model file written before the key existed was trained in), ``scan``
            (the partial's own centroid and radius), ``aligned`` (that frame turned to the
            partial's main horizontal axis), ``aligned-end`` (the same, pointing to the
            axis's sparser end), ``aligned-rim`` (turned by the quarter turn that brings the
            cut's rim nearest +x), ``rim`` (the scan frame turned so that the rim lies at +x)
            or ``heading`` (the scan frame turned back by the heading
            :mod:`pfnet.data.heading`'s reader reads).
    """

    model: str = "pfnet"
    n_points: int | None = None
    missing_ratio: float = 0.25
    width: float = 1.0
    frame: str = "shape"

    def __post_init__(self) -> None:
        check_model_config(self)
        check_missing_count(self)

    @property
    def n_missing(self) -> int:
        """M, the number of missing points (``round(missing_ratio · n_points)``)."""
        from pfnet.data import missing_count

        if self.n_points is None:
            raise ConfigError("n_points is not set (it is taken from the dataset when training)")
        return missing_count(self.n_points, self.missing_ratio)

    def replace(self, **changes: Any) -> Self:
        """A copy with ``changes`` applied (``None`` values are ignored), validated."""
        unknown = sorted(set(changes) - set(self.keys()))
        if unknown:
            raise ConfigError(
                f"unknown config key(s) {', '.join(unknown)}; valid: {', '.join(self.keys())}"
            )
        return dataclasses.replace(self, **{k: v for k, v in changes.items() if v is not None})

    @classmethod
    def keys(cls) -> tuple[str, ...]:
        """The names of the settings, in order."""
        return tuple(f.name for f in dataclasses.fields(cls))

    def to_dict(self) -> dict[str, Any]:
        """Plain dict of builtins (lists, not tuples): JSON- and ``weights_only``-safe."""
        return {key: _plain(value) for key, value in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(
        cls, data: dict[str, Any], *, source: str = "config", extra: str = "refuse"
    ) -> Self:
        """Build from a plain dict, naming ``source`` in any :class:`ConfigError`.

        Args:
            data: Settings by name; missing ones take their defaults.
            source: What the dict was read from (a file, a checkpoint).
            extra: ``"refuse"`` unknown keys, or ``"ignore"`` them (a :class:`ModelConfig`
                read from a checkpoint's training configuration).
        """
        if not isinstance(data, dict):
            raise ConfigError(f"{source}: expected a table of settings, got {type(data).__name__}")
        keys = cls.keys()
        unknown = sorted(str(k) for k in set(data) - set(keys))
        if unknown and extra == "refuse":
            raise ConfigError(
                f"{source}: unknown key(s) {', '.join(unknown)}; valid keys: {', '.join(keys)}"
            )
        try:
            return cls(**{k: v for k, v in data.items() if k in keys})
        except ConfigError as err:
            raise ConfigError(f"{source}: {err}") from None

    def model_config(self) -> ModelConfig:
        """Only the network's settings (a :class:`ModelConfig`, not a subclass)."""
        return ModelConfig(**{k: getattr(self, k) for k in ModelConfig.keys()})


def _plain(value: Any) -> Any:
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    return value


def is_int(value: Any) -> bool:
    """An ``int`` and not a ``bool``."""
    return isinstance(value, int) and not isinstance(value, bool)


def is_number(value: Any) -> bool:
    """A finite ``int`` or ``float`` (not a ``bool``)."""
    return (is_int(value) or isinstance(value, float)) and math.isfinite(value)


_REPR = reprlib.Repr()
_REPR.maxstring = _REPR.maxother = 80
_REPR.maxlevel, _REPR.maxlist, _REPR.maxdict = 3, 4, 4


def require(ok: bool, key: str, value: Any, what: str) -> None:
    """Raise :class:`ConfigError` ``"{key} must be {what}; got {value}"`` unless ``ok``."""
    if not ok:
        # reprlib bounds the text (a forged value nested 80 levels deep would be 2^80 long)
        raise ConfigError(f"{key} must be {what}; got {_REPR.repr(value)}")


def check_model_config(c: ModelConfig) -> None:
    """Raise :class:`ConfigError` naming the first invalid network setting of ``c``."""
    require(c.model in MODEL_NAMES, "model", c.model, f"one of {', '.join(MODEL_NAMES)}")
    require(
        c.n_points is None or (is_int(c.n_points) and 8 <= c.n_points <= MAX_POINTS),
        "n_points",
        c.n_points,
        f"an integer in [8, {MAX_POINTS}] (or unset)",
    )
    require(
        is_number(c.missing_ratio) and 0 < c.missing_ratio < 1,
        "missing_ratio",
        c.missing_ratio,
        "a number in (0, 1)",
    )
    require(is_number(c.width) and 0 < c.width <= 4, "width", c.width, "a number in (0, 4]")
    require(c.frame in FRAMES, "frame", c.frame, f"one of {', '.join(FRAMES)}")


def check_missing_count(c: ModelConfig) -> None:
    """Raise :class:`ConfigError` unless ``c``'s crop leaves 1 to N - 4 points missing."""
    if c.n_points is not None:
        m = c.n_missing
        if not 1 <= m <= c.n_points - 4:
            raise ConfigError(
                f"missing_ratio {c.missing_ratio} of {c.n_points} points removes {m} points; "
                f"at least 1 must be missing and 4 must remain"
            )
