"""benchmarks/surface_oracle.py: a fresh sample of the true surface scored by the test protocol."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from brute import nearest_distances
from scripts import load_script

from pfnet.data import load_split, prepare_dataset, test_protocol_crop
from pfnet.data.crops import test_protocol_viewpoints


@pytest.fixture(scope="module")
def surface_oracle():
    return load_script("surface_oracle")


@pytest.fixture(scope="module")
def pooled(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Procedural meshes, 256 points a shape and a pool of 768 (two fresh clouds more)."""
    out = tmp_path_factory.mktemp("oracle") / "pooled"
    prepare_dataset(
        None,
        out,
        format="procedural",
        points=256,
        pool=768,
        seed=0,
        count=4,
        categories=["chair", "table"],
        test_fraction=0.5,
        val_fraction=0.0,
        workers=1,
        progress=False,
    )
    return out


def _naive_row(prediction: np.ndarray, truth: np.ndarray, threshold: float) -> dict:
    """Pred→GT, GT→Pred (×1000) and F-score of one prediction, by brute force."""
    to_gt, to_pred = nearest_distances(prediction, truth), nearest_distances(truth, prediction)
    precision, recall = (to_gt < threshold).mean(), (to_pred < threshold).mean()
    f = 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)
    return {"pred_to_gt": 1e3 * (to_gt**2).mean(), "gt_to_pred": 1e3 * (to_pred**2).mean(), "f": f}


def test_the_oracle_is_the_pool_cropped_at_the_test_viewpoint(surface_oracle, pooled, tmp_path):
    threshold = 0.05
    out = tmp_path / "oracle.json"
    assert (
        surface_oracle.main(["--data", str(pooled), "--threshold", "0.05", "--json", str(out)]) == 0
    )
    scores = json.loads(out.read_text())
    assert scores["samples"] == 2  # --samples 3 asked, the pool holds two clouds more

    clouds = load_split(pooled, "test")
    partial, removed = test_protocol_crop(clouds.points, 0.25)
    viewpoints = test_protocol_viewpoints(len(clouds))
    naive: dict[str, list[dict]] = {}
    floor: dict[str, list[dict]] = {}
    for i, category in enumerate(clouds.category.tolist()):
        for k in range(2):  # an independent crop: the 64 pool points nearest the viewpoint
            fresh = clouds.extra[i, 256 * k : 256 * (k + 1)]
            near = np.argsort(np.linalg.norm(fresh - viewpoints[i], axis=1), kind="stable")[:64]
            naive.setdefault(category, []).append(_naive_row(fresh[near], removed[i], threshold))
        near = np.argsort(np.linalg.norm(partial[i] - viewpoints[i], axis=1), kind="stable")[:64]
        floor.setdefault(category, []).append(_naive_row(partial[i][near], removed[i], threshold))
    for computed, reference in ((scores["oracle"], naive), (scores["floor"], floor)):
        assert sorted(computed["categories"]) == ["chair", "table"]
        means = {key: [] for key in ("pred_to_gt", "gt_to_pred", "f")}
        for category, rows in reference.items():
            got = computed["categories"][category]
            for key in means:
                expected = np.mean([r[key] for r in rows])
                means[key].append(expected)
                assert got["f_score" if key == "f" else key] == pytest.approx(expected, rel=1e-4)
        mean = computed["mean"]
        assert mean["cd_l2"] == pytest.approx(
            np.mean(means["pred_to_gt"]) + np.mean(means["gt_to_pred"]), rel=1e-4
        )
        assert mean["f_score"] == pytest.approx(np.mean(means["f"]), rel=1e-4)
    # a fresh sample of the right surface is far closer than the input's own points
    assert scores["oracle"]["mean"]["cd_l2"] < scores["floor"]["mean"]["cd_l2"] / 5


def test_a_data_set_without_a_pool_or_from_point_files_is_refused(
    surface_oracle, pooled, tiny_dataset, tmp_path
):
    with pytest.raises(
        SystemExit, match=r"^error: .*needs a pool of at least 1024 points a shape .*has 512"
    ):
        surface_oracle.main(["--data", str(tiny_dataset)])
    points = tmp_path / "points"
    (points / "blob").mkdir(parents=True)
    for n in range(10):
        np.savetxt(
            points / "blob" / f"shape{n}.xyz", np.random.default_rng(n).normal(size=(300, 3))
        )
    prepared = tmp_path / "from-points"
    prepare_dataset(points, prepared, points=128, pool=512, seed=0, workers=1, progress=False)
    with pytest.raises(SystemExit, match=r"^error: .*prepared from 'meshes'; only mesh sources"):
        surface_oracle.main(["--data", str(prepared)])
    with pytest.raises(SystemExit, match=r"^error: missing_ratio must be in \(0, 1\), got 1.5$"):
        surface_oracle.main(["--data", str(pooled), "--missing-ratio", "1.5"])


def test_at_high_ratios_the_floor_is_the_whole_partial_input(surface_oracle, pooled):
    scores = surface_oracle.oracle_scores(pooled, "test", 0.75, 1, 0.05)  # keeps 64 of 256
    clouds = load_split(pooled, "test")
    partial, removed = test_protocol_crop(clouds.points, 0.75)
    rows = [_naive_row(p, r, 0.05) for p, r in zip(partial, removed, strict=True)]
    categories = clouds.category.tolist()
    expected = np.mean(
        [
            np.mean([r["pred_to_gt"] for r, c in zip(rows, categories) if c == cat])
            for cat in set(categories)
        ]
    )
    assert scores["floor"]["mean"]["pred_to_gt"] == pytest.approx(expected, rel=1e-4)
    assert scores["oracle"]["mean"]["cd_l2"] < scores["floor"]["mean"]["cd_l2"] / 5


def test_several_mesh_sources_qualify_and_one_point_source_among_them_does_not(
    surface_oracle, pooled, tmp_path, capsys
):
    """open-shapes' airplanes come from FlightGear and crrcsim (AC3D meshes): their pools are
    fresh surface samples; a ``meshes`` folder among the sources may be point files."""
    import shutil

    several = tmp_path / "several"
    shutil.copytree(pooled, several)
    manifest = json.loads((several / "manifest.json").read_text())
    sources = [{"format": "flightgear", "path": "/fg"}, {"format": "crrcsim", "path": "/cs"}]
    manifest["source"] = {"format": "several", "sources": sources}
    (several / "manifest.json").write_text(json.dumps(manifest))
    scores = {}
    for name, data in (("several", several), ("procedural", pooled)):
        out = tmp_path / f"{name}.json"
        assert surface_oracle.main(["--data", str(data), "--json", str(out)]) == 0
        scores[name] = json.loads(out.read_text())["oracle"]
    assert scores["several"] == scores["procedural"]  # the same clouds, the same scores
    sources.append({"format": "meshes", "path": "/mine"})
    (several / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(
        SystemExit, match=r"^error: .*prepared from several sources, among them 'meshes'; only"
    ):
        surface_oracle.main(["--data", str(several)])
