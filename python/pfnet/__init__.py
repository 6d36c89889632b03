"""pfnet: PF-Net point cloud completion with a Rust geometry core.

The geometry core (``pfnet.geometry``) needs only numpy; the model, training and
inference parts import torch when they are used, never at ``import pfnet``.

Completing a scan from Python::

    import numpy as np, pfnet
    result = pfnet.complete(np.loadtxt("scan.xyz"), up="z")
    result.missing, result.completed
"""

from importlib.metadata import PackageNotFoundError, version

from pfnet import geometry

try:
    __version__ = version("pfnet-completion")  # the distribution's name ("pfnet" is taken)
except PackageNotFoundError:  # running from a source tree without an install
    __version__ = "0.0.0"

__all__ = ["Completion", "complete", "geometry", "load_model", "__version__"]

# Imported on first use, so that `import pfnet` stays as light as the geometry core.
_LAZY = {
    "complete": "pfnet.inference.completion",
    "load_model": "pfnet.inference.completion",
    "Completion": "pfnet.inference.completion",
}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'pfnet' has no attribute {name!r}")
