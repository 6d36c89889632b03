"""Tests for ``pfnet evaluate``: numbers against a naive numpy computation, every bad file."""

from __future__ import annotations

import csv
import json
import shutil

import numpy as np
import pytest

from pfnet.cli import main
from pfnet.data import load_split, missing_count
from pfnet.errors import ConfigError, DataError
from pfnet.evaluation.scoring import evaluate_predictions, find_prediction_files
from pfnet.io.clouds import save_npy, write_ply
from pfnet.viz.gallery import pick_gallery

# The authors' crop centres (DESIGN.md §3), written out here so the test does not reuse the
# code under test.
VIEWPOINTS = np.array([[1, 0, 0], [0, 0, 1], [1, 0, 1], [-1, 0, 0], [-1, 1, 0]], np.float64)


def naive_crop(points: np.ndarray, index: int, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Sample ``index`` of the test protocol: drop the round(r·N) points nearest its viewpoint."""
    m = missing_count(len(points), ratio)
    distance = np.linalg.norm(points.astype(np.float64) - VIEWPOINTS[index % 5], axis=1)
    order = np.argsort(distance, kind="stable")
    keep = np.sort(order[m:])
    return points[keep], points[np.sort(order[:m])]


def naive_terms(pred: np.ndarray, gt: np.ndarray) -> tuple[float, float, float, float]:
    """(pred_to_gt, gt_to_pred, cd_l1, f_score@0.01) with a full distance matrix."""
    d2 = ((pred[:, None, :].astype(np.float64) - gt[None, :, :]) ** 2).sum(-1)
    p2g, g2p = d2.min(axis=1), d2.min(axis=0)
    cd_l1 = (np.sqrt(p2g).mean() + np.sqrt(g2p).mean()) / 2
    precision, recall = (np.sqrt(p2g) < 0.01).mean(), (np.sqrt(g2p) < 0.01).mean()
    f = 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)
    return p2g.mean(), g2p.mean(), cd_l1, f


def naive_report(data_dir, predictions: dict[str, np.ndarray], ratio: float, region: str):
    """Per-category means (×1000 for the Chamfer terms) and their unweighted mean."""
    clouds = load_split(data_dir, "test")
    rows: dict[str, list] = {}
    for i, (cat, name) in enumerate(zip(clouds.category, clouds.name, strict=True)):
        key = f"{cat}/{name}"
        if key not in predictions:
            continue
        partial, removed = naive_crop(np.asarray(clouds.points[i]), i, ratio)
        if region == "missing":
            terms = naive_terms(predictions[key], removed)
        else:
            merged = np.concatenate([partial, predictions[key]])
            terms = naive_terms(merged, np.asarray(clouds.points[i]))
        rows.setdefault(str(cat), []).append(terms)
    categories = {}
    for cat, terms in rows.items():
        t = np.mean(terms, axis=0)
        categories[cat] = {
            "n": len(terms),
            "pred_to_gt": t[0] * 1000,
            "gt_to_pred": t[1] * 1000,
            "cd_l1": t[2],
            "f_score": t[3],
        }
    mean = {
        k: float(np.mean([c[k] for c in categories.values()]))
        for k in ("pred_to_gt", "gt_to_pred", "cd_l1", "f_score")
    }
    return categories, mean


def write_predictions(folder, data_dir, ratio, make, suffix=".npy", skip=()):
    """Write ``make(i, partial, removed, complete)`` for every test sample; return them."""
    clouds = load_split(data_dir, "test")
    out = {}
    for i, (cat, name) in enumerate(zip(clouds.category, clouds.name, strict=True)):
        key = f"{cat}/{name}"
        if key in skip:
            continue
        complete = np.asarray(clouds.points[i])
        partial, removed = naive_crop(complete, i, ratio)
        pred = np.asarray(make(i, partial, removed, complete), dtype=np.float32)
        (folder / str(cat)).mkdir(parents=True, exist_ok=True)
        path = folder / str(cat) / f"{name}{suffix}"
        if suffix == ".npy":
            save_npy(path, pred)
        elif suffix == ".ply":
            write_ply(path, pred)
        else:
            np.savetxt(path, pred, fmt="%.9g")
        out[key] = pred
    return out


def assert_report_matches(report, categories, mean, rtol=1e-5, atol=1e-9):
    assert set(report["categories"]) == set(categories)
    for cat, expected in categories.items():
        got = report["categories"][cat]
        assert got["n"] == expected["n"]
        for key in ("pred_to_gt", "gt_to_pred", "cd_l1", "f_score"):
            assert got[key] == pytest.approx(expected[key], rel=rtol, abs=atol), (cat, key)
    for key, value in mean.items():
        assert report["mean"][key] == pytest.approx(value, rel=rtol, abs=atol), key


@pytest.fixture(scope="module")
def test_keys(tiny_dataset) -> list[str]:
    clouds = load_split(tiny_dataset, "test")
    return [f"{c}/{n}" for c, n in zip(clouds.category, clouds.name, strict=True)]


def test_perfect_predictions_score_zero(tmp_path, tiny_dataset, test_keys):
    write_predictions(tmp_path, tiny_dataset, 0.25, lambda i, p, r, c: r)
    result = evaluate_predictions(tmp_path, tiny_dataset)
    report = result.report
    assert report["mean"] == {"pred_to_gt": 0.0, "gt_to_pred": 0.0, "cd_l1": 0.0, "f_score": 1.0}
    assert sum(c["n"] for c in report["categories"].values()) == len(test_keys)
    assert report["missing"] == [] and report["unreadable"] == []


def test_shift_smaller_than_half_the_spacing_gives_d_squared(tmp_path, tiny_dataset):
    # Shifting every point by d < s/2 (s = smallest gap between ground-truth points) keeps
    # each point's nearest neighbour, so both Chamfer terms are exactly d².
    shifts = {}

    def shifted(i, partial, removed, complete):
        gaps = np.linalg.norm(removed[:, None] - removed[None], axis=-1)
        gaps[np.diag_indices(len(removed))] = np.inf
        shifts[i] = 0.4 * float(gaps.min())
        return removed.astype(np.float64) + [shifts[i], 0.0, 0.0]

    write_predictions(tmp_path, tiny_dataset, 0.25, shifted)
    result = evaluate_predictions(tmp_path, tiny_dataset)
    clouds = load_split(tiny_dataset, "test")
    by_cat: dict[str, list[float]] = {}
    for i, cat in enumerate(clouds.category):
        by_cat.setdefault(str(cat), []).append(shifts[i] ** 2 * 1000)
    for cat, values in by_cat.items():
        got = result.report["categories"][cat]
        assert got["pred_to_gt"] == pytest.approx(np.mean(values), rel=1e-2)
        assert got["gt_to_pred"] == pytest.approx(np.mean(values), rel=1e-2)


@pytest.mark.parametrize("ratio", [0.25, 0.5])
def test_missing_region_matches_naive(tmp_path, tiny_dataset, ratio):
    rng = np.random.default_rng(3)

    def noisy(i, partial, removed, complete):
        # A different point count than the ground truth, and noise at the F-score scale.
        pred = removed[rng.integers(0, len(removed), size=100)]
        return pred + rng.normal(scale=0.01, size=pred.shape)

    preds = write_predictions(tmp_path, tiny_dataset, ratio, noisy)
    result = evaluate_predictions(tmp_path, tiny_dataset, missing_ratio=ratio)
    categories, mean = naive_report(tiny_dataset, preds, ratio, "missing")
    assert_report_matches(result.report, categories, mean)
    assert result.report["missing_ratio"] == ratio and result.report["region"] == "missing"


def test_whole_region_merges_partial_input(tmp_path, tiny_dataset):
    rng = np.random.default_rng(4)
    preds = write_predictions(
        tmp_path,
        tiny_dataset,
        0.25,
        lambda i, p, r, c: r + rng.normal(scale=0.02, size=r.shape),
        suffix=".ply",
    )
    result = evaluate_predictions(tmp_path, tiny_dataset, region="whole")
    categories, mean = naive_report(tiny_dataset, preds, 0.25, "whole")
    assert_report_matches(result.report, categories, mean)


def test_whole_region_of_complete_predictions(tmp_path, tiny_dataset):
    write_predictions(tmp_path, tiny_dataset, 0.25, lambda i, p, r, c: c, suffix=".xyz")
    result = evaluate_predictions(tmp_path, tiny_dataset, region="whole", pred_is_complete=True)
    assert result.report["mean"]["pred_to_gt"] == 0.0
    assert result.report["mean"]["f_score"] == 1.0
    # Read as missing regions instead, the same files are far from the removed points.
    result = evaluate_predictions(tmp_path, tiny_dataset, region="missing")
    assert result.report["mean"]["pred_to_gt"] > 1.0


def test_cli_json_csv_exact_schema(tmp_path, tiny_dataset, test_keys, capsys):
    pred = tmp_path / "pred"
    rng = np.random.default_rng(5)
    preds = write_predictions(
        pred, tiny_dataset, 0.25, lambda i, p, r, c: r + rng.normal(scale=0.01, size=r.shape)
    )
    js, cs = tmp_path / "out" / "m.json", tmp_path / "m.csv"
    js.parent.mkdir()
    code = main(
        ["evaluate", str(pred), "--data", str(tiny_dataset), "--json", str(js), "--csv", str(cs)]
    )
    assert code == 0
    out = capsys.readouterr().out
    assert "Pred→GT" in out and "GT→Pred" in out and "mean" in out and "F@0.01" in out
    report = json.loads(js.read_text())
    assert list(report) == [
        "region",
        "scale",
        "missing_ratio",
        "categories",
        "mean",
        "missing",
        "unreadable",
    ]
    assert report["region"] == "missing" and report["scale"] == 1000
    for row in report["categories"].values():
        assert list(row) == ["n", "pred_to_gt", "gt_to_pred", "cd_l1", "f_score"]
        assert isinstance(row["n"], int)
    assert list(report["mean"]) == ["pred_to_gt", "gt_to_pred", "cd_l1", "f_score"]
    categories, mean = naive_report(tiny_dataset, preds, 0.25, "missing")
    assert_report_matches(report, categories, mean)
    with open(cs, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [f"{r['category']}/{r['name']}" for r in rows] == test_keys
    first = rows[0]
    p2g, g2p, l1, f = naive_terms(
        preds[test_keys[0]],
        naive_crop(np.asarray(load_split(tiny_dataset, "test").points[0]), 0, 0.25)[1],
    )
    assert float(first["pred_to_gt"]) == pytest.approx(p2g * 1000, rel=1e-4)
    assert float(first["gt_to_pred"]) == pytest.approx(g2p * 1000, rel=1e-4)
    assert float(first["cd_l2"]) == pytest.approx((p2g + g2p) * 1000, rel=1e-4)
    assert float(first["cd_l1"]) == pytest.approx(l1 * 1000, rel=1e-4)
    assert float(first["f_score"]) == pytest.approx(f, abs=1e-6)


def test_missing_and_bad_files_are_listed_and_excluded(tmp_path, tiny_dataset, test_keys, capsys):
    pred = tmp_path / "pred"
    lost, garbage, empty, nan, short = test_keys[:5]
    preds = write_predictions(pred, tiny_dataset, 0.25, lambda i, p, r, c: r, skip={lost})
    for key in (garbage, empty, nan, short):
        (pred / f"{key}.npy").unlink()
    (pred / f"{garbage}.npy").write_bytes(b"not numpy")
    np.save(pred / f"{empty}.npy", np.zeros((0, 3), np.float32))
    np.save(pred / f"{nan}.npy", np.full((4, 3), np.nan, np.float32))
    (pred / f"{short}.txt").write_text("1 2\n")
    (pred / "extra").mkdir()
    save_npy(pred / "extra" / "stray.npy", np.zeros((3, 3)))
    js = tmp_path / "m.json"

    code = main(["evaluate", str(pred), "--data", str(tiny_dataset), "--json", str(js)])
    captured = capsys.readouterr()
    assert code == 2
    report = json.loads(js.read_text())
    assert report["missing"] == [lost]
    assert report["unreadable"] == [k for k in test_keys if k in {garbage, empty, nan, short}]
    assert sum(c["n"] for c in report["categories"].values()) == len(test_keys) - 5
    err = captured.err
    assert f"missing: 1 sample(s) have no prediction file: {lost}" in err
    assert "not a valid .npy array file" in err and "holds no points" in err
    assert "NaN or infinite" in err and "line 1 has 2 column" in err
    assert "1 prediction file(s) match no sample" in err and "stray.npy" in err
    assert "--allow-missing" in err
    scored = {k: v for k, v in preds.items() if k not in {garbage, empty, nan, short}}
    categories, mean = naive_report(tiny_dataset, scored, 0.25, "missing")
    assert_report_matches(report, categories, mean)

    code = main(["evaluate", str(pred), "--data", str(tiny_dataset), "--allow-missing"])
    assert code == 0


def test_suffixes_and_lookup(tmp_path):
    (tmp_path / "chair").mkdir()
    for name in ("a.npy", "b.xyz", ".hidden.npy", ".hidden.ply", "c.obj"):
        (tmp_path / "chair" / name).write_text("")
    (tmp_path / "loose.npy").write_text("")
    files = find_prediction_files(tmp_path)
    assert {k: v.name for k, v in files.items()} == {"chair/a": "a.npy", "chair/b": "b.xyz"}
    (tmp_path / "chair" / "b.pts").write_text("")  # two files of one sample: refused (issue 36)
    with pytest.raises(DataError, match=r"b\.pts and .*b\.xyz are two predictions"):
        find_prediction_files(tmp_path)


def test_pick_gallery_round_robin():
    cats = ["b", "a", "a", "c", "a", "b"]
    assert pick_gallery(cats, 4) == [1, 0, 3, 2]
    assert pick_gallery(cats, 100) == [1, 0, 3, 2, 5, 4]
    assert pick_gallery([], 3) == []


def test_gallery(tmp_path, tiny_dataset):
    pred = tmp_path / "pred"
    write_predictions(pred, tiny_dataset, 0.25, lambda i, p, r, c: r)
    png = tmp_path / "g.png"
    args = ["evaluate", str(pred), "--data", str(tiny_dataset), "--gallery", str(png)]
    assert main([*args, "--gallery-count", "2"]) == 0
    assert png.read_bytes()[:4] == b"\x89PNG"
    assert main([*args, "--gallery-count", "0"]) == 1


def test_errors(tmp_path, tiny_dataset, capsys):
    with pytest.raises(DataError, match="prediction folder .* does not exist"):
        evaluate_predictions(tmp_path / "nope", tiny_dataset)
    # The library speaks of its parameters, the command of its options.
    with pytest.raises(ConfigError, match=r"^complete predictions \(pred_is_complete\) need"):
        evaluate_predictions(tmp_path, tiny_dataset, pred_is_complete=True)
    with pytest.raises(ConfigError, match=r"^missing ratio must be in \(0, 1\)"):
        evaluate_predictions(tmp_path, tiny_dataset, missing_ratio=1.0)
    with pytest.raises(ConfigError, match="^region must be one of"):
        evaluate_predictions(tmp_path, tiny_dataset, region="half")
    base = ["evaluate", str(tmp_path), "--data", str(tiny_dataset)]
    assert main([*base, "--pred-is-complete"]) == 1
    assert "error: --pred-is-complete needs --region whole" in capsys.readouterr().err
    assert main([*base, "--missing-ratio", "1"]) == 1
    assert "error: --missing-ratio must be in (0, 1), got 1.0" in capsys.readouterr().err
    with pytest.raises(DataError, match=r"no prediction in .* could be scored .* 0 unreadable"):
        evaluate_predictions(tmp_path, tiny_dataset)
    assert main(["evaluate", str(tmp_path), "--data", str(tmp_path / "no-data")]) == 1
    assert capsys.readouterr().err.startswith("pfnet evaluate: error: ")


def test_every_sample_unreadable_is_an_error(tmp_path, tiny_dataset, test_keys):
    write_predictions(tmp_path, tiny_dataset, 0.25, lambda i, p, r, c: r)
    for key in test_keys:
        (tmp_path / f"{key}.npy").write_bytes(b"")
    with pytest.raises(DataError, match=rf"0 missing, {len(test_keys)} unreadable"):
        evaluate_predictions(tmp_path, tiny_dataset)
    shutil.rmtree(tmp_path)


def test_pcd_predictions_are_found_and_scored(tmp_path, tiny_dataset):
    from pfnet.data import test_protocol_crop

    clouds = load_split(tiny_dataset, "test")
    _, removed = test_protocol_crop(np.asarray(clouds.points), 0.25)
    for category, name, cloud in zip(clouds.category, clouds.name, removed, strict=True):
        head = (
            "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
            f"WIDTH {len(cloud)}\nHEIGHT 1\nPOINTS {len(cloud)}\nDATA binary\n"
        )
        (tmp_path / category).mkdir(exist_ok=True)
        (tmp_path / category / f"{name}.pcd").write_bytes(head.encode() + cloud.tobytes())
    assert all(p.suffix == ".pcd" for p in find_prediction_files(tmp_path).values())
    result = evaluate_predictions(tmp_path, tiny_dataset, missing_ratio=0.25)
    assert result.report["mean"]["pred_to_gt"] == 0.0 and not result.missing
