"""Hostile output locations: no command deletes or overwrites its inputs, or writes outside
its --out, whatever the paths and names it is given (issue #14's worst class)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from forge import write_predictions

from pfnet.cli import main
from pfnet.data import load_split
from pfnet.data.format import CloudSet
from pfnet.errors import DataError
from pfnet.io.clouds import read_point_cloud, write_ply


def _tree(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` with its bytes: what must survive a refused command."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def _mesh_folder(folder: Path) -> Path:
    """A folder of two small OBJ meshes (a category folder each), and an unrelated file."""
    import trimesh

    for category, mesh in (
        ("chair", trimesh.creation.box()),
        ("lamp", trimesh.creation.icosphere()),
    ):
        (folder / category).mkdir(parents=True)
        mesh.export(folder / category / f"{category}_1.obj")
    (folder / "notes.txt").write_text("the user's own file")
    return folder


@pytest.mark.parametrize("where", ["source", "parent", "inside", "symlink"])
def test_prepare_never_writes_over_or_around_its_source(tmp_path: Path, where: str, capsys) -> None:
    source = _mesh_folder(tmp_path / "home" / "meshes")
    (tmp_path / "home" / "thesis.tex").write_text("unrelated work")
    before = _tree(tmp_path / "home")
    out = {
        "source": source,
        "parent": source.parent,
        "inside": source / "dataset",
        "symlink": tmp_path / "link",
    }[where]
    if where == "symlink":
        out.symlink_to(source)
    args = ["prepare", str(source), "--out", str(out), "--points", "64", "--overwrite"]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "the input" in err and "apart from the inputs" in err, err
    assert _tree(tmp_path / "home") == before


def test_prepare_overwrite_replaces_only_an_earlier_data_set(tmp_path: Path, capsys) -> None:
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "precious.txt").write_text("not a data set")
    args = ["prepare", "procedural", "--count", "2", "--points", "64", "--overwrite"]
    assert main([*args, "--out", str(mine)]) == 1
    assert "is not a pfnet data set" in capsys.readouterr().err
    assert (mine / "precious.txt").read_text() == "not a data set"
    data = tmp_path / "data"
    assert main([*args, "--out", str(data)]) == 0
    assert main([*args, "--out", str(data), "--seed", "1"]) == 0  # an earlier data set: replaced


def test_complete_never_overwrites_an_input(tmp_path: Path, capsys) -> None:
    pytest.importorskip("torch")
    rng = np.random.default_rng(0)
    a, a_missing = tmp_path / "a.ply", tmp_path / "a_missing.ply"
    write_ply(a, rng.normal(size=(300, 3)).astype(np.float32))
    write_ply(a_missing, rng.normal(size=(200, 3)).astype(np.float32))
    before = _tree(tmp_path)
    assert main(["complete", str(a), str(a_missing), "--out", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "would overwrite the input" in err and "a_missing.ply" in err
    assert _tree(tmp_path) == before
    (tmp_path / "file").write_text("x")
    assert main(["complete", str(a), "--out", str(tmp_path / "file")]) == 1
    assert "is a file" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("category", "name", "message"),
    [
        ("chair", "../../escaped", "not allowed in a file name"),
        ("..", "x", "is not a name"),
        ("/tmp", "x", "not allowed in a file name"),
        ("chair", "", "is empty"),
        ("chair", "a\x00b", "not allowed in a file name"),
        (".x", "a", "begins with '.'"),  # predict wrote these; evaluate skipped them
        ("chair", ".a", "begins with '.'"),
    ],
)
def test_names_that_would_leave_the_output_folder_are_refused_on_load(
    tmp_path: Path, category: str, name: str, message: str
) -> None:
    points = np.zeros((2, 8, 3), np.float32)
    with pytest.raises(DataError, match=message):
        CloudSet(points, np.array(["chair", category]), np.array(["ok", name]))


def test_a_data_set_with_hostile_or_duplicate_names_cannot_be_loaded(
    tmp_path: Path, tiny_dataset: Path
) -> None:
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    # forge the test split as an attacker would: names written straight into the npz
    n = len(load_split(data, "test"))  # as many rows as the manifest records
    others = [f"shape_{i}" for i in range(n - 2)]
    for names, message in (
        (["../../../outside", "b", *others], "not allowed in a file name"),
        (["b", "b", *others], "chair/b appears twice"),
    ):
        points = np.zeros((n, 512, 3), np.float32)
        np.savez(data / "test.npz", points=points, category=np.array(["chair"] * n), name=names)
        with pytest.raises(DataError, match=message):
            load_split(data, "test")
    # a category the manifest does not list; one named like predict's record file
    names = ["a", *others, "b"]
    for odd, message in (
        ("zebra", r"categories \[.zebra.\] are not in the manifest"),
        ("predictions.json", "category 'predictions.json' is the name of the record predict"),
    ):
        category = np.array(["chair"] * (n - 1) + [odd])
        np.savez(data / "test.npz", points=points, category=category, name=names)
        with pytest.raises(DataError, match=message):
            load_split(data, "test")


def test_evaluate_refuses_hidden_names_it_would_never_find(
    tmp_path: Path, tiny_dataset: Path, capsys
) -> None:
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    clouds = load_split(data, "test")
    names = clouds.name.copy()
    names[0] = ".a"  # once written by predict as PRED/<category>/.a.npy, then reported missing
    np.savez(data / "test.npz", points=clouds.points, category=clouds.category, name=names)
    pred = tmp_path / "pred"
    pred.mkdir()
    assert main(["evaluate", str(pred), "--data", str(data)]) == 1
    err = capsys.readouterr().err
    assert "test.npz" in err and "'.a' begins with '.'" in err and "Traceback" not in err


def test_predict_and_train_refuse_an_output_over_their_data(
    tmp_path: Path, tiny_dataset: Path, capsys
) -> None:
    pytest.importorskip("torch")
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    before = _tree(data)
    for command in (["predict", "--checkpoint", str(data / "manifest.json")], ["train"]):
        for out in (data, tmp_path, data / "inner"):
            assert main([*command, "--data", str(data), "--out", str(out)]) == 1
            assert "apart from the inputs" in capsys.readouterr().err
    assert _tree(data) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]


def test_evaluate_and_render_outputs_never_replace_inputs(
    tmp_path: Path, tiny_dataset: Path, capsys
) -> None:
    pred = write_predictions(tmp_path / "pred", tiny_dataset)
    victim = next(pred.rglob("*.npy"))
    before = _tree(tmp_path)
    base = ["evaluate", str(pred), "--data", str(tiny_dataset)]
    assert main([*base, "--json", str(victim)]) == 1
    assert "inside a subfolder of the prediction folder" in capsys.readouterr().err
    assert main([*base, "--json", str(pred / victim.name)]) == 1
    assert "would overwrite a file of the prediction folder" in capsys.readouterr().err
    # anything in the data set, not only the split being scored (the audit's train.npz)
    for name in ("test.npz", "train.npz", "new-report.json"):
        assert main([*base, "--csv", str(tiny_dataset / name)]) == 1
        assert "is inside the input" in capsys.readouterr().err
    # a prediction file that another suffix shadows, and the predictions record
    shadowed = victim.with_suffix(".ply")
    write_ply(shadowed, read_point_cloud(victim))
    (pred / "predictions.json").write_text("{}")
    before = _tree(tmp_path)
    for target, message in (
        (shadowed, "inside a subfolder of the prediction folder"),
        (pred / shadowed.name, "would overwrite a file of the prediction folder"),
        (pred / "predictions.json", "would overwrite a file of the prediction folder"),
    ):
        assert main([*base, "--json", str(target), "--ignore-recorded-protocol"]) == 1
        assert message in capsys.readouterr().err
    (pred / "predictions.json").unlink()
    shadowed.unlink()  # two files of one sample are refused by evaluate (issue 36)
    # an earlier report in the prediction folder may be replaced
    report = pred / "metrics.json"
    assert main([*base, "--json", str(report)]) == 0 and main([*base, "--json", str(report)]) == 0
    report.unlink()
    capsys.readouterr()
    before = _tree(tmp_path)
    assert main([*base, "--json", str(pred)]) == 1
    assert "is a folder" in capsys.readouterr().err
    assert _tree(tmp_path) == before
    cloud = tmp_path / "cloud.ply"
    write_ply(cloud, read_point_cloud(victim))
    (tmp_path / "figures.png").mkdir()
    assert main(["render", str(cloud), "--out", str(tmp_path / "figures.png")]) == 1
    assert "is a folder" in capsys.readouterr().err
