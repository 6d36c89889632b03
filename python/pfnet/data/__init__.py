"""Completion datasets: ``pfnet prepare`` and the readers of its format (DESIGN.md §3).

Importing ``pfnet.data`` needs neither torch nor trimesh; the torch ``Dataset`` lives in
:mod:`pfnet.data.dataset`.
"""

from pfnet.data.crops import (
    VIEWS,
    every_view,
    missing_count,
    test_protocol_crop,
    test_protocol_viewpoints,
)
from pfnet.data.format import SPLITS, CloudSet, load_split, read_manifest
from pfnet.data.prepare import prepare_dataset
from pfnet.data.prepared import PrepareReport
from pfnet.data.sources.sweethome3d import DEFAULT_PATH as SWEETHOME3D_PATH

__all__ = [
    "SPLITS",
    "SWEETHOME3D_PATH",
    "VIEWS",
    "CloudSet",
    "every_view",
    "PrepareReport",
    "load_split",
    "missing_count",
    "prepare_dataset",
    "read_manifest",
    "test_protocol_crop",
    "test_protocol_viewpoints",
]
