"""Forged inputs shared by the hostile-input tests (imported as `forge`: pytest puts this
folder on sys.path)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pfnet.data import load_split, test_protocol_crop


def write_predictions(
    folder: Path,
    data: Path,
    *,
    ratio: float = 0.25,
    split: str = "test",
    record: bool = False,
    skip: tuple[str, ...] = (),
) -> Path:
    """A prediction folder laid out as `pfnet predict` writes it: each sample's true missing
    region under the test protocol (categories in ``skip`` left out), and with ``record`` the
    ``predictions.json`` that names the split and ratio."""
    clouds = load_split(data, split)
    _, removed = test_protocol_crop(np.asarray(clouds.points), ratio)
    for category, name, cloud in zip(clouds.category, clouds.name, removed, strict=True):
        if category in skip:
            continue
        (folder / category).mkdir(parents=True, exist_ok=True)
        np.save(folder / category / f"{name}.npy", cloud)
    if record:
        info = {"split": split, "protocol": {"name": "test", "missing_ratio": ratio}}
        (folder / "predictions.json").write_text(json.dumps(info))
    return folder
