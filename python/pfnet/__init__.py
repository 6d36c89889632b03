"""pfnet: PF-Net point cloud completion with a Rust geometry core.

The geometry core (``pfnet.geometry``) needs only numpy; the model, training and
inference parts import torch when they are used, never at ``import pfnet``.
"""

from importlib.metadata import PackageNotFoundError, version

from pfnet import geometry

try:
    __version__ = version("pfnet-completion")  # the distribution's name ("pfnet" is taken)
except PackageNotFoundError:  # running from a source tree without an install
    __version__ = "0.0.0"

__all__ = ["geometry", "__version__"]
