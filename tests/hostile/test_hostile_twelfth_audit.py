"""The twelfth hostile audit's breaks: pictures written through a planted link (W1), symbolic
link loops as paths (X1), ``$`` in names and titles (X2), an unbounded ``reproduce
--gallery-count`` (V1) and an F-score threshold beyond float64 (M1)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from pfnet.cli import main
from pfnet.errors import ConfigError


@pytest.fixture
def scan(tmp_path: Path) -> Path:
    path = tmp_path / "scan.xyz"
    np.savetxt(path, np.random.default_rng(0).random((300, 3)))
    return path


def test_pictures_replace_a_planted_link_never_write_through_it(
    tmp_path: Path, scan: Path, tiny_dataset: Path
) -> None:
    from forge import write_predictions

    victim = tmp_path / "outside" / "keep.txt"
    victim.parent.mkdir()
    victim.write_text("keep")
    pred = write_predictions(tmp_path / "pred", tiny_dataset)
    pictures = tmp_path / "pictures"
    pictures.mkdir()
    commands = {
        "render.png": ["render", str(scan), "--out"],
        "render.html": ["render", str(scan), "--html"],
        "gallery.png": ["evaluate", str(pred), "--data", str(tiny_dataset), "--gallery"],
    }
    if importlib.util.find_spec("plotly") is None:  # the viewer's extra is not installed
        del commands["render.html"]
    for name, command in commands.items():
        link = pictures / name
        link.symlink_to(victim)
        assert main([*command, str(link)]) == 0
        assert not link.is_symlink() and link.stat().st_size > 1000, name
        assert victim.read_text() == "keep", name


def test_a_symbolic_link_loop_is_one_line(
    tmp_path: Path, scan: Path, tiny_dataset: Path, capsys
) -> None:
    loop = tmp_path / "L1"
    loop.symlink_to(tmp_path / "L2")
    (tmp_path / "L2").symlink_to(loop)
    for args in (
        ["complete", str(scan), "--out", str(loop)],
        ["render", str(loop), "--out", str(tmp_path / "r.png")],
        ["prepare", "procedural", "--out", str(loop), "--points", "512", "--count", "3"],
        ["predict", "--data", str(loop), "--out", str(tmp_path / "p")],
    ):
        assert main(args) == 1, args
        err = capsys.readouterr().err
        assert f"error: a symbolic link loop: '{tmp_path}" in err, args
        assert "Traceback" not in err


def test_dollar_signs_in_names_and_titles_are_text(tmp_path: Path, scan: Path) -> None:
    named = tmp_path / "x$^^$.xyz"
    named.write_bytes(scan.read_bytes())
    assert main(["render", str(named), "--out", str(tmp_path / "m.png")]) == 0
    title = "$\\undefinedmacro$"
    assert main(["render", str(scan), "--out", str(tmp_path / "t.png"), "--title", title]) == 0


@pytest.mark.parametrize("count", ["0", "-5", "201"])
def test_reproduce_gallery_count_is_bounded(tmp_path: Path, count: str, capsys) -> None:
    out = tmp_path / "study"
    assert main(["reproduce", "--report-only", "--out", str(out), "--gallery-count", count]) == 1
    assert f"--gallery-count must be in [1, 200], got {count}" in capsys.readouterr().err
    assert not out.exists()


def test_an_f_score_threshold_beyond_float64_is_refused() -> None:
    from pfnet.evaluation.metrics import sample_metrics

    cloud = np.zeros((1, 4, 3), np.float32)
    with pytest.raises(ConfigError, match="f_threshold must be a positive finite distance"):
        sample_metrics(cloud, cloud, f_threshold=10**400)


def test_options_given_in_vain_or_twice_are_refused(
    tmp_path: Path, tiny_dataset: Path, capsys
) -> None:
    """Audit 12 notes N2, N4: one file for two reports, options of another protocol or
    without the option they qualify."""
    from forge import write_predictions

    pred = write_predictions(tmp_path / "pred", tiny_dataset)
    base = ["evaluate", str(pred), "--data", str(tiny_dataset)]
    same = str(tmp_path / "r.txt")
    for extra, message in (
        (["--json", same, "--csv", same], "--json, --csv and --gallery name the same file"),
        (["--gallery-count", "5"], "--gallery-count applies only with --gallery"),
        (["--reference-category", "chair"], "--reference-category applies to the kitti protocol"),
    ):
        assert main([*base, *extra]) == 1, extra
        assert message in capsys.readouterr().err
    assert not Path(same).exists()
    out = tmp_path / "p"
    predict = ["predict", "--data", str(tiny_dataset), "--out", str(out), "--gallery-count", "3"]
    assert main(predict) == 1
    assert "--gallery-count applies only with --gallery" in capsys.readouterr().err
    assert not out.exists()


def test_train_refuses_other_folders_and_runs_sized_twice_or_beyond_bounds(
    tmp_path: Path, tiny_dataset: Path, capsys
) -> None:
    """Audit 12 notes N3b, N5."""
    from forge import write_predictions

    pred = write_predictions(tmp_path / "pred", tiny_dataset)
    (pred / "predictions.json").write_text("{}")  # as pfnet predict leaves it
    before = sorted(p.name for p in pred.iterdir())
    train = ["train", "--data", str(tiny_dataset), "--device", "cpu", "--out"]
    import shutil

    other = tmp_path / "other-data"
    shutil.copytree(tiny_dataset, other)
    for out, message in (
        (other, "is a prepared data set; name a folder for the run"),
        (pred, "is a prediction folder; name a folder for the run"),
    ):
        assert main([*train, str(out), "--steps", "1"]) == 1
        assert message in capsys.readouterr().err
    assert sorted(p.name for p in pred.iterdir()) == before
    run = str(tmp_path / "run")
    for extra, message in (
        (["--steps", "2", "--epochs", "3"], "--epochs and --steps size the run two ways"),
        (["--steps", str(10**12)], "steps must be an integer in [1, 100,000,000]"),
        (["--epochs", str(10**12)], "epochs must be an integer in [1, 1,000,000]"),
    ):
        assert main([*train, run, *extra]) == 1, extra
        assert message in capsys.readouterr().err
    assert not Path(run).exists()


@pytest.mark.parametrize(
    "categories, names, message",
    [
        (["chair\u202eriahc", "chair"], ["a", "b"], "contains the invisible"),
        (["chair", "chair"], ["a", " "], "is only spaces"),
        (["chair", "chair"], ["cabinet_1", "CABINET_1"], "differ only in case"),
        (["Chair", "chair"], ["a", "b"], "categories Chair and chair differ only in case"),
    ],
)
def test_names_that_display_or_land_as_other_names_are_refused(
    categories: list[str], names: list[str], message: str
) -> None:
    """Audit 12 note N9: names are file names (PRED/<category>/<name>.npy)."""
    from pfnet.data.format import CloudSet
    from pfnet.errors import DataError

    with pytest.raises(DataError, match=message):
        CloudSet(np.zeros((2, 4, 3), np.float32), np.array(categories), np.array(names))


def test_a_split_with_a_non_finite_cloud_is_named_when_loaded(
    tmp_path: Path, tiny_dataset: Path
) -> None:
    """Audit 12 note N6: a NaN in test.npz was reported by a geometry call, without a file."""
    import shutil

    from pfnet.data import load_split
    from pfnet.errors import DataError

    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    test = load_split(data, "test")
    points = test.points.copy()
    points[2, 5, 1] = np.inf
    np.savez(data / "test.npz", points=points, category=test.category, name=test.name)
    shape = f"{test.category[2]}/{test.name[2]}"
    with pytest.raises(DataError, match=f"test.npz: shape {shape} \\(index 2\\) holds NaN or inf"):
        load_split(data, "test")


def test_a_checkpoint_whose_config_builds_no_network_is_named(tmp_path: Path) -> None:
    """Audit 12 note N6: an empty config said "n_points is not set", not which file."""
    pytest.importorskip("torch")
    from pfnet.errors import DataError
    from pfnet.inference.checkpoint import load_checkpoint, save_checkpoint
    from pfnet.models import build_model
    from pfnet.training.config import preset_config

    config = preset_config("small").replace(n_points=512, width=0.125)
    path = tmp_path / "empty-config.pt"
    save_checkpoint(path, {"config": {}, "model": build_model(config).state_dict()})
    with pytest.raises(DataError, match=f"checkpoint {path}: n_points is not set"):
        load_checkpoint(path)
