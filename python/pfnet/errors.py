"""Exceptions raised by pfnet for bad input or bad files (the CLI prints them in one line).

``GeometryError`` is defined by the Rust core (``pfnet._core``, where a class can be raised from
Rust) and re-exported here, its public home: every error of the core and every bad value given to
``pfnet.geometry`` is one. It is a ``ValueError`` but not a ``PfnetError``.
"""

from pfnet._core import GeometryError

__all__ = ["ConfigError", "DataError", "GeometryError", "PfnetError"]


class PfnetError(Exception):
    """Base class of pfnet's own errors; the CLI prints its message and exits non-zero."""


class DataError(PfnetError, ValueError):
    """A dataset, point cloud or prediction file is missing, unreadable or malformed."""


class ConfigError(PfnetError, ValueError):
    """A configuration value is out of range or of the wrong type."""


class MissingDependency(PfnetError):
    """An optional dependency is not installed; the message names the extra to install."""
