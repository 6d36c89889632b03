"""pfnet.evaluation.metrics against direct numpy computations."""

import numpy as np
import pytest

from pfnet.evaluation.metrics import sample_metrics, summarize


def naive_metrics(p, t, thr):
    d = ((p[:, None, :].astype(np.float64) - t[None, :, :]) ** 2).sum(-1)
    pg, gp = d.min(1), d.min(0)
    prec, rec = (pg < thr**2).mean(), (gp < thr**2).mean()
    f = 0.0 if prec + rec == 0 else 2 * prec * rec / (prec + rec)
    return {
        "pred_to_gt": pg.mean(),
        "gt_to_pred": gp.mean(),
        "cd_l2": pg.mean() + gp.mean(),
        "cd_l1": 0.5 * (np.sqrt(pg).mean() + np.sqrt(gp).mean()),
        "f_score": f,
    }


def test_sample_metrics_batched_and_lists_match_numpy():
    rng = np.random.default_rng(0)
    pred = rng.uniform(-1, 1, (4, 64, 3)).astype(np.float32)
    gt = (pred + rng.normal(0, 0.01, pred.shape)).astype(np.float32)
    got = sample_metrics(pred, gt, f_threshold=0.02)
    as_lists = sample_metrics(list(pred), [g[:50] for g in gt], f_threshold=0.02)
    for i in range(4):
        want = naive_metrics(pred[i], gt[i], 0.02)
        want_list = naive_metrics(pred[i], gt[i][:50], 0.02)
        for name, value in want.items():
            assert got[name][i] == pytest.approx(value, rel=1e-5, abs=1e-12), name
            assert as_lists[name][i] == pytest.approx(want_list[name], rel=1e-5, abs=1e-12)


def test_perfect_and_shifted_predictions():
    gt = np.random.default_rng(1).uniform(-1, 1, (2, 100, 3)).astype(np.float32)
    perfect = sample_metrics(gt, gt)
    assert perfect["cd_l2"].tolist() == [0.0, 0.0] and perfect["f_score"].tolist() == [1.0, 1.0]
    single = np.zeros((1, 1, 3), np.float32)
    shifted = sample_metrics(single + np.float32([0.1, 0, 0]), single)
    assert shifted["pred_to_gt"][0] == pytest.approx(0.01, rel=1e-6)
    assert shifted["cd_l1"][0] == pytest.approx(0.1, rel=1e-6)
    assert shifted["f_score"][0] == 0.0


def test_summarize_is_the_unweighted_mean_of_category_means():
    per_sample = {"pred_to_gt": [1e-3, 3e-3, 2e-3], "f_score": [0.5, 0.7, 0.9]}
    table = summarize(per_sample, ["chair", "chair", "lamp"])
    assert table["categories"]["chair"] == {
        "n": 2,
        "pred_to_gt": pytest.approx(2.0),
        "f_score": pytest.approx(0.6),
    }
    assert table["categories"]["lamp"]["pred_to_gt"] == pytest.approx(2.0)
    # Unweighted: (2.0 + 2.0) / 2 and (0.6 + 0.9) / 2, not the mean over the 3 samples.
    assert table["mean"] == {"pred_to_gt": pytest.approx(2.0), "f_score": pytest.approx(0.75)}


def test_errors_name_the_mismatch():
    with pytest.raises(ValueError, match="as many clouds, got 2 and 1"):
        sample_metrics([np.zeros((3, 3))] * 2, [np.zeros((3, 3))])
    with pytest.raises(ValueError, match=r"shape \(2,\) but there are 3 categories"):
        summarize({"pred_to_gt": [1, 2]}, ["a", "b", "c"])
