"""Forged inputs shared by the hostile-input tests (imported as `forge`: pytest puts this
folder on sys.path)."""

from __future__ import annotations

import json
import shutil
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


def resized_dataset(folder: Path, data: Path, n_points: int) -> Path:
    """A copy of ``data`` whose test clouds hold ``n_points`` points each (the first ones,
    repeated cyclically when there are fewer), its manifest saying so."""
    shutil.copytree(data, folder)
    clouds = load_split(folder, "test")
    index = np.arange(n_points) % clouds.points.shape[1]
    np.savez(
        folder / "test.npz",
        points=np.ascontiguousarray(clouds.points[:, index]),
        category=clouds.category,
        name=clouds.name,
    )
    manifest = json.loads((folder / "manifest.json").read_text())
    (folder / "manifest.json").write_text(json.dumps({**manifest, "points": n_points}))
    return folder


def onnx_model(
    path: Path,
    nodes: list,
    *,
    n_points: int = 512,
    detail_shape: list | None = None,
    detail_type: int | None = None,
    initializers: tuple = (),
) -> Path:
    """A forged ONNX graph ``partial (batch, points, 3) -> detail`` carrying the metadata of a
    pfnet export for ``n_points``-point clouds (ratio 0.25), so it passes the metadata checks.
    ``detail`` is declared float ``(batch, M, 3)`` unless told otherwise."""
    import onnx
    from onnx import TensorProto, helper

    from pfnet.inference.onnx_graph import FORMAT, VERSION
    from pfnet.models.config import ModelConfig

    config = ModelConfig(n_points=n_points)
    shape = ["batch", config.n_missing, 3] if detail_shape is None else detail_shape
    graph = helper.make_graph(
        nodes,
        path.stem,
        [helper.make_tensor_value_info("partial", TensorProto.FLOAT, ["batch", "points", 3])],
        [helper.make_tensor_value_info("detail", detail_type or TensorProto.FLOAT, shape)],
        initializer=list(initializers),
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    meta = {
        "format": FORMAT,
        "version": VERSION,
        "n_points": str(config.n_points),
        "n_missing": str(config.n_missing),
        "config": json.dumps(config.to_dict()),
    }
    for key, value in meta.items():
        model.metadata_props.append(onnx.StringStringEntryProto(key=key, value=value))
    onnx.save(model, path)
    return path
