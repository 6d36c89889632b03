"""benchmarks/fit_check.py: the fit check's report and its perfect-completion reference."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")  # the fit check trains (the light install has no torch)

from scripts import load_script  # noqa: E402

from pfnet.data import load_split, prepare_dataset  # noqa: E402
from pfnet.errors import DataError  # noqa: E402


@pytest.fixture(scope="module")
def fit_check():
    return load_script("fit_check")


@pytest.fixture(scope="module")
def surface_oracle():
    return load_script("surface_oracle")


def _prepare(
    out: Path, pool: int | None, seed: int = 0, categories: tuple[str, ...] = ("chair", "table")
) -> Path:
    prepare_dataset(
        None,
        out,
        format="procedural",
        points=512,
        pool=pool,
        seed=seed,
        count=3,
        categories=list(categories),
        test_fraction=0.34,
        val_fraction=0.0,
        workers=1,
        progress=False,
    )
    return out


@pytest.fixture(scope="module")
def meshes(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The same procedural shapes prepared without and with a pool of 1,536 points."""
    root = tmp_path_factory.mktemp("fit")
    return _prepare(root / "plain", None), _prepare(root / "pooled", 1536)


def test_the_report_has_the_surface_oracle_of_the_fit_shapes(
    fit_check, surface_oracle, meshes, tmp_path, capsys
):
    plain, pooled = meshes
    out = tmp_path / "fit"
    args = ["--data", str(plain), "--out", str(out), "--shapes", "2", "--batch-size", "2"]
    args += ["--steps", "2", "--device", "cpu", "--oracle-data", str(pooled)]
    assert fit_check.main(args) in (0, 1)
    printed = capsys.readouterr().out
    report = json.loads(printed[printed.index("{\n") :])
    # the oracle's shapes are the fit check's, with the pools the pooled data set holds
    fit = load_split(out / "data", "train")
    oracle = load_split(out / "oracle", "val")
    assert oracle.name.tolist() == fit.name.tolist() and len(fit) == 2
    np.testing.assert_array_equal(oracle.points, fit.points)
    source = load_split(pooled, "train")
    by_name = {n: i for i, n in enumerate(source.name.tolist())}
    for i, name in enumerate(fit.name.tolist()):
        np.testing.assert_array_equal(oracle.extra[i], source.extra[by_name[name]])
    expected = surface_oracle.oracle_scores(out / "oracle", "val", 0.25, 3, 0.01)
    assert expected["samples"] == 2  # the pool holds two clouds more, not three
    assert report["surface_oracle"] == {"samples": 2} | expected["oracle"]["mean"]
    assert 0 < report["surface_oracle"]["cd_l2"] < report["val_cd_l2_best_last_tenth"]
    assert 0 <= report["val_f_score_at_the_best"] <= 1


def test_an_oracle_data_set_without_the_shapes_or_their_clouds_is_refused(
    fit_check, meshes, tmp_path
):
    plain, _ = meshes
    lamps = _prepare(tmp_path / "lamps", 1536, categories=("lamp",))
    other = _prepare(tmp_path / "other-seed", 1536, seed=1)
    cases = [
        (plain, "has no pool of surface points (pfnet prepare --pool)"),
        (lamps, "does not hold the fit check's shape"),
        (other, "holds another cloud of"),
    ]
    for data, message in cases:
        out = tmp_path / f"fit-{data.name}"
        args = ["--data", str(plain), "--out", str(out), "--shapes", "2"]
        with pytest.raises(DataError, match=re.escape(message)):
            fit_check.main([*args, "--steps", "2", "--oracle-data", str(data)])
        assert not (out / "run").exists()  # refused before any training
