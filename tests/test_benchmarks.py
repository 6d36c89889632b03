"""The benchmarks of later work (issue 17): PCN and ShapeNet-55/34 layouts through prepare,
predict and evaluate; PoinTr's metrics and crop against independent computations; KITTI's
Fidelity and MMD against every pair."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from brute import capture_panels, naive_fps, nearest_distances, needs_runtime, write_pcd

from pfnet.cli import main
from pfnet.data import load_split, prepare_dataset
from pfnet.data.benchmarks import load_partials
from pfnet.data.categories import SHAPENET_SYNSETS, category_title
from pfnet.errors import ConfigError, DataError
from pfnet.evaluation.benchmarks import evaluate_benchmark
from pfnet.evaluation.metrics import fidelity, minimal_matching_distance, sample_metrics
from pfnet.evaluation.protocols import SHAPENET_VIEWPOINTS, get_protocol, shapenet_crop

SH3D = Path("/usr/share/sweethome3d/furniture/BlendSwap-CC-0.sh3f")


# ---------------------------------------------------------------- independent references


def pointr_reference(pred: np.ndarray, gt: np.ndarray, th: float = 0.01) -> dict[str, float]:
    """PoinTr's formulas written out with all-pairs distances (float64): CD-L1, CD-L2 with
    ignore_zeros (points whose x+y+z == 0 left out), F-score on Euclidean distances."""

    def dists(a, b):
        return np.sqrt(
            ((a[:, None, :].astype(np.float64) - b[None].astype(np.float64)) ** 2).sum(-1)
        )

    p = pred[pred.sum(axis=1) != 0]
    g = gt[gt.sum(axis=1) != 0]
    d = dists(p, g)
    d1, d2 = d.min(axis=1), d.min(axis=0)
    full = dists(pred, gt)
    precision = float((full.min(axis=1) < th).mean())
    recall = float((full.min(axis=0) < th).mean())
    f = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    return {
        "cd_l1": (d1.mean() + d2.mean()) / 2,
        "cd_l2": (d1**2).mean() + (d2**2).mean(),
        "f_score": f,
    }


# ---------------------------------------------------------------- trees in the documented layouts


def real_clouds(count: int, n_points: int) -> list[np.ndarray]:
    """Surface samples of real SweetHome3D models (procedural shapes without the package)."""
    from pfnet.data.sampling import sample_surface
    from pfnet.data.sources.registry import load_item

    rng = np.random.default_rng(0)
    if SH3D.is_file():
        from pfnet.data.sources import sweethome3d

        items = sweethome3d.scan(SH3D, strict=False).items[:count]
    else:  # pragma: no cover
        from pfnet.data.sources import procedural

        items = procedural.scan(count).items[:count]
    clouds = []
    for item in items:
        mesh = load_item(item, 0)
        cloud = sample_surface(mesh.vertices, mesh.faces, n_points, rng)
        cloud = (cloud - cloud.mean(axis=0)) / np.abs(cloud).max() / 2  # PCN-like scale
        clouds.append(cloud.astype(np.float32))
    return clouds


@pytest.fixture(scope="module")
def pcn_tree(tmp_path_factory) -> Path:
    """A PCN tree (PoinTr's DATASET.md): real meshes, 16,384-point complete clouds, partial
    scans 00..07 in train and 00 in val/test, PCN.json and category.txt."""
    root = tmp_path_factory.mktemp("pcn") / "PCN"
    clouds = iter(real_clouds(12, 16384))
    records = []
    for taxonomy, name in (("02691156", "airplane"), ("03001627", "chair")):
        record = {"taxonomy_id": taxonomy, "taxonomy_name": name}
        for split, n in (("train", 2), ("val", 1), ("test", 3)):
            record[split] = []
            for k in range(n):
                model = f"{taxonomy[-3:]}{split}{k}e2b8f3c1"
                record[split].append(model)
                cloud = next(clouds)
                write_pcd(root / split / "complete" / taxonomy / f"{model}.pcd", cloud)
                for view in range(8 if split == "train" else 1):
                    seen = cloud[cloud @ SHAPENET_VIEWPOINTS[view] > 0][: 900 + 50 * k]
                    write_pcd(root / split / "partial" / taxonomy / model / f"{view:02d}.pcd", seen)
        records.append(record)
    (root / "PCN.json").write_text(json.dumps(records, indent=4))
    (root / "category.txt").write_text("airplane\nchair\n")
    return root


@pytest.fixture(scope="module")
def shapenet_tree(tmp_path_factory) -> Path:
    """A ShapeNet55-34 tree: shapenet_pc/<taxonomy>-<model>.npy of 8,192 points (real meshes,
    not normalised) and the ShapeNet-55 / ShapeNet-34 split lists."""
    root = tmp_path_factory.mktemp("sn") / "ShapeNet55-34"
    (root / "shapenet_pc").mkdir(parents=True)
    lists: dict[str, list[str]] = {"train": [], "test": []}
    clouds = iter(real_clouds(8, 8192))
    for taxonomy in ("02691156", "04379243"):
        for split, n in (("train", 2), ("test", 2)):
            for k in range(n):
                file = f"{taxonomy}-{split}{k}a9c0d7e.npy"
                np.save(root / "shapenet_pc" / file, next(clouds) * 37.0 + 5.0)
                lists[split].append(file)
    for folder in ("ShapeNet-55", "ShapeNet-34"):
        (root / folder).mkdir()
        for split, files in lists.items():
            (root / folder / f"{split}.txt").write_text("\n".join(files) + "\n")
    return root


# ---------------------------------------------------------------- metrics and protocols


def test_metrics_equal_pointr_formulas_computed_independently():
    rng = np.random.default_rng(3)
    pred = rng.normal(size=(700, 3)).astype(np.float32) * 0.05
    gt = rng.normal(size=(900, 3)).astype(np.float32) * 0.05
    pred[:5] = [1.0, -1.0, 0.0]  # x + y + z = 0: PoinTr's ignore_zeros drops them
    got = sample_metrics([pred], [gt], ignore_zeros=True)
    want = pointr_reference(pred, gt)
    for key in ("cd_l1", "cd_l2", "f_score"):
        assert got[key][0] == pytest.approx(want[key], rel=1e-6), key
    plain = sample_metrics([pred], [gt])
    assert plain["cd_l2"][0] > got["cd_l2"][0]  # the far zero-sum points count without it


def test_crop_equals_an_independent_crop_and_fps():
    rng = np.random.default_rng(1)
    cloud = rng.normal(size=(8192, 3)).astype(np.float32)
    for view, ratio in ((0, 0.25), (5, 0.5), (7, 0.75)):
        d = np.linalg.norm(cloud.astype(np.float64) - SHAPENET_VIEWPOINTS[view], axis=1)
        kept = cloud[np.argsort(d, kind="stable")[int(8192 * ratio) :]]
        np.testing.assert_array_equal(shapenet_crop(cloud, ratio, view), naive_fps(kept, 2048))


def test_shapenet_synsets_are_named():
    assert len(SHAPENET_SYNSETS) == 55 and len(set(SHAPENET_SYNSETS.values())) == 55
    assert all(len(s) == 8 and s.isdigit() for s in SHAPENET_SYNSETS)
    assert category_title("03001627") == "03001627 chair"
    assert category_title("chair") == "chair" and category_title("12345678") == "12345678"


def test_protocols_are_named_objects():
    assert get_protocol("shapenet34") is get_protocol("shapenet55")
    assert get_protocol("pcn").headline == "cd_l1"
    assert get_protocol("shapenet55").sample_keys("a", "b")[7] == "a/b_view7"
    with pytest.raises(ConfigError, match="protocol must be one of pfnet, pcn, shapenet55"):
        get_protocol("kitti-cars")


def test_fidelity_and_mmd_equal_every_pair():
    rng = np.random.default_rng(5)
    refs = np.stack([rng.normal(size=(300, 3)) * rng.uniform(0.5, 1.5, 3) for _ in range(25)])
    comps = np.stack([refs[j] * 1.02 + 0.01 for j in (3, 17, 9)]).astype(np.float32)
    refs = refs.astype(np.float32)
    dist, index = minimal_matching_distance(comps, refs)
    for k, comp in enumerate(comps):
        every = []
        for ref in refs:
            d1 = nearest_distances(comp, ref)
            d2 = nearest_distances(ref, comp)
            every.append((d1**2).mean() + (d2**2).mean())
        assert index[k] == int(np.argmin(every))
        assert dist[k] == pytest.approx(min(every), rel=1e-6)
    partial = comps[:, :100]
    want = [(nearest_distances(p, c) ** 2).mean() for p, c in zip(partial, comps, strict=True)]
    np.testing.assert_allclose(fidelity(partial, comps), want, rtol=1e-6)
    with pytest.raises(ValueError, match="references must be a"):
        minimal_matching_distance(comps, refs[0])


# ---------------------------------------------------------------- end to end


@pytest.mark.slow  # end to end, or a measurement: runs in CI, not the default run
@needs_runtime
def test_pcn_prepare_predict_evaluate(pcn_tree, tmp_path, monkeypatch):
    data, pred = tmp_path / "data", tmp_path / "pred"
    assert main(["prepare", str(pcn_tree), "--out", str(data)]) == 0
    test = load_split(data, "test")
    assert test.points.shape == (6, 16384, 3) and test.categories == ["airplane", "chair"]
    original = np.fromfile(pcn_tree / "test/complete/02691156/156test0e2b8f3c1.pcd", np.uint8)
    assert len(original) > 16384 * 12  # coordinates kept as given (no normalisation)
    partials = load_partials(data, "test", len(test))
    assert [len(p) for p in partials] == [900, 950, 1000, 900, 950, 1000]
    assert main(["predict", "--data", str(data), "--out", str(pred), "--protocol", "pcn"]) == 0
    completion = np.load(pred / "airplane" / f"{test.name[0]}.npy")
    np.testing.assert_array_equal(completion[:900], partials[0])  # the scan, then 512 points
    assert completion.shape == (900 + 512, 3)
    js = tmp_path / "r.json"
    assert main(["evaluate", str(pred), "--data", str(data), "--json", str(js)]) == 0
    report = json.loads(js.read_text())
    assert report["protocol"] == "pcn" and report["categories"]["chair"]["n"] == 3
    cloud = np.load(pred / "airplane" / f"{test.name[0]}.npy")  # the first score, again
    want = pointr_reference(cloud, test.points[0])
    got = evaluate_benchmark(pred, data, "pcn").per_sample
    assert got["cd_l1"][0] == pytest.approx(want["cd_l1"], rel=1e-6)
    assert got["f_score"][0] == pytest.approx(want["f_score"], rel=1e-6)
    means = [report["categories"][c]["cd_l1"] for c in ("airplane", "chair")]
    assert report["mean"]["cd_l1"] == pytest.approx(np.mean(means))

    # the gallery: the given scan, the completion file, the complete cloud; spread over categories
    drawn, gallery = capture_panels(monkeypatch), tmp_path / "g.png"
    args = ["evaluate", str(pred), "--data", str(data), "--gallery", str(gallery)]
    assert main([*args, "--gallery-count", "3"]) == 0
    assert gallery.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    (rows,) = drawn
    assert [label for label, _ in rows] == [
        f"airplane/{test.name[0]}",
        f"chair/{test.name[3]}",
        f"airplane/{test.name[1]}",
    ]
    for (label, panels), i in zip(rows, (0, 3, 1), strict=True):
        assert [title for title, _ in panels] == ["input", "completion", "ground truth"]
        np.testing.assert_array_equal(panels[0][1][0][0], partials[i])
        np.testing.assert_array_equal(panels[1][1][0][0], np.load(pred / f"{label}.npy"))
        np.testing.assert_array_equal(panels[2][1][0][0], test.points[i])


@pytest.mark.slow  # end to end, or a measurement: runs in CI, not the default run
@needs_runtime
def test_shapenet55_prepare_predict_evaluate(shapenet_tree, tmp_path, capsys, monkeypatch):
    data, pred = tmp_path / "data", tmp_path / "pred"
    assert main(["prepare", str(shapenet_tree), "--out", str(data)]) == 0
    assert "04379243 table" in capsys.readouterr().out  # synsets named in the summary
    test = load_split(data, "test")
    assert test.points.shape == (4, 8192, 3)
    assert np.linalg.norm(test.points, axis=2).max() == pytest.approx(1.0, abs=1e-5)  # pc_norm
    args = ["--data", str(data), "--out", str(pred), "--protocol", "shapenet55"]
    drawn, gallery = capture_panels(monkeypatch), tmp_path / "g.png"
    assert main(["predict", *args, "--missing-ratio", "0.75", "--gallery", str(gallery)]) == 0
    assert gallery.read_bytes()[:4] == b"\x89PNG"
    # one view per shape (shape j: view j % 8), PoinTr's crop of it, named with the synset
    (rows,) = drawn
    shapes = [f"{c}/{n}" for c, n in zip(test.category, test.name, strict=True)]
    want = [shapes[0] + "_view0", shapes[2] + "_view2", shapes[1] + "_view1", shapes[3] + "_view3"]
    assert [label for label, _ in rows] == [
        key.replace("02691156", "02691156 airplane").replace("04379243", "04379243 table")
        for key in want
    ]
    for (_, panels), i in zip(rows, (0, 2, 1, 3), strict=True):
        view = i  # shape i, in the split's order, shows view i % 8
        crop = shapenet_crop(test.points[i], 0.75, view)
        np.testing.assert_array_equal(panels[0][1][0][0], crop)
        np.testing.assert_array_equal(panels[2][1][0][0], test.points[i])
    files = sorted((pred / "02691156").glob("*.npy"))
    assert len(files) == 16 and files[0].name.endswith("_view0.npy")
    first = np.load(files[0])
    np.testing.assert_array_equal(first[:2048], shapenet_crop(test.points[0], 0.75, 0))
    capsys.readouterr()
    js = tmp_path / "r.json"
    assert main(["evaluate", str(pred), "--data", str(data), "--json", str(js)]) == 0
    out = capsys.readouterr().out
    assert "protocol shapenet55, 75% missing, 32 of 32 completions scored" in out
    assert "02691156 airplane" in out and "04379243 table" in out  # synsets named
    report = json.loads(js.read_text())
    want = pointr_reference(first, test.points[0])
    got = evaluate_benchmark(pred, data, "shapenet55", missing_ratio=0.75).per_sample
    assert got["cd_l2"][0] == pytest.approx(want["cd_l2"], rel=1e-6)
    assert report["categories"]["02691156"]["n"] == 16
    # the record lists each shape once with its 8 endings; --overwrite with another split
    # removes exactly those files, and none while a file of the user's is among them
    record = json.loads((pred / "predictions.json").read_text())
    endings = [f"_view{v}.npy" for v in range(8)]
    assert record["files"] == {
        "endings": endings,
        "names": {c: sorted(test.name[test.category == c]) for c in test.categories},
    }
    np.save(pred / "04379243" / "mine_view0.npy", first)
    before = sorted(pred.rglob("*"))
    assert main(["predict", *args, "--split", "train", "--overwrite"]) == 1
    assert "does not list (04379243/mine_view0.npy)" in capsys.readouterr().err
    assert sorted(pred.rglob("*")) == before
    (pred / "04379243" / "mine_view0.npy").unlink()
    assert main(["predict", *args, "--split", "train", "--overwrite"]) == 0
    train = load_split(data, "train")
    assert sorted(str(p.relative_to(pred)) for p in pred.rglob("*.npy")) == sorted(
        f"{c}/{n}{e}" for c, n in zip(train.category, train.name, strict=True) for e in endings
    )
    assert (
        main(
            [
                "prepare",
                str(shapenet_tree),
                "--out",
                str(tmp_path / "d34"),
                "--format",
                "shapenet-34",
            ]
        )
        == 0
    )


# ---------------------------------------------------------------- error paths


def test_pcn_bad_files_are_named_and_the_rest_prepared(pcn_tree, tmp_path):
    broken = tmp_path / "PCN"
    import shutil

    shutil.copytree(pcn_tree, broken)
    (broken / "test/partial/03001627/627test1e2b8f3c1/00.pcd").unlink()
    (broken / "test/complete/02691156/156test2e2b8f3c1.pcd").write_text("not a pcd")
    report = prepare_dataset(broken, tmp_path / "d", progress=False)
    reasons = dict(report.skipped)
    assert (
        "the partial scan 00.pcd is missing"
        in reasons[str(broken / "test/partial/03001627/627test1e2b8f3c1/00.pcd")]
    )
    assert str(broken / "test/complete/02691156/156test2e2b8f3c1.pcd") in reasons
    assert report.counts["test"] == {"airplane": 2, "chair": 2}
    (broken / "PCN.json").write_text("{not json")
    with pytest.raises(DataError, match="PCN.json: cannot read the category file"):
        prepare_dataset(broken, tmp_path / "d2", progress=False)


@needs_runtime
def test_benchmark_option_errors(pcn_tree, tiny_dataset, tmp_path, capsys):
    data = tmp_path / "data"
    prepare_dataset(pcn_tree, data, progress=False)
    with pytest.raises(ConfigError, match="keeps its own clouds: points, pool and count"):
        prepare_dataset(pcn_tree, tmp_path / "x", points=2048, progress=False)
    with pytest.raises(DataError, match="no partial scans; the pcn protocol needs"):
        load_partials(tiny_dataset, "test", 12)
    with pytest.raises(ConfigError, match="takes no missing ratio"):
        evaluate_benchmark(tmp_path, data, "pcn", missing_ratio=0.25)
    pred = tmp_path / "pred"
    assert main(["predict", "--data", str(data), "--out", str(pred), "--protocol", "pcn"]) == 0
    capsys.readouterr()
    assert main(["evaluate", str(pred), "--data", str(data), "--region", "whole"]) == 1
    assert "--region applies to the pfnet protocol, not to pcn" in capsys.readouterr().err
    assert main(["evaluate", str(pred), "--data", str(data), "--protocol", "shapenet55"]) == 1
    assert "made with the pcn protocol" in capsys.readouterr().err
    next(iter((pred / "chair").glob("*.npy"))).unlink()
    assert main(["evaluate", str(pred), "--data", str(data)]) == 2
    assert "1 sample(s) have no prediction file: chair/" in capsys.readouterr().err
