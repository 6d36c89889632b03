"""The second hostile audit's findings: pictures over inputs, unbounded config reads, damaged
resume states, --overwrite and user files, symlinked outputs, case-only name clashes, text
files with a byte-order mark or trailing comments."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from forge import write_predictions

from pfnet.cli import main
from pfnet.evaluation.prediction_record import MAX_RECORD_BYTES
from pfnet.io.clouds import read_point_cloud, write_ply


def _tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


@pytest.fixture
def checkpoint(tmp_path: Path) -> Path:
    pytest.importorskip("torch")
    from pfnet.inference.checkpoint import save_checkpoint
    from pfnet.models import build_model
    from pfnet.training.config import preset_config

    config = preset_config("small").replace(n_points=512, width=0.125)
    path = tmp_path / "m.pt"
    save_checkpoint(path, {"config": config.to_dict(), "model": build_model(config).state_dict()})
    return path


def test_predict_gallery_never_lands_on_its_inputs(
    tmp_path: Path, tiny_dataset: Path, checkpoint: Path, capsys
) -> None:
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    pred = write_predictions(tmp_path / "pred", data)
    victim = next(pred.rglob("*.npy"))
    before = _tree(tmp_path)
    base = ["predict", "--checkpoint", str(checkpoint), "--data", str(data), "--out", str(pred)]
    for gallery, message in (
        (data / "test.npz", "must be a .png file"),  # a gallery is a PNG: never a data file,
        (checkpoint, "must be a .png file"),  # a checkpoint or a prediction
        (victim, "must be a .png file"),
        (data / "g.png", "is inside the input"),
        (pred / ".hidden.png", "would overwrite a file of the prediction folder"),
    ):
        assert main([*base, "--device", "cpu", "--gallery", str(gallery)]) == 1
        assert message in capsys.readouterr().err
    assert _tree(tmp_path) == before


def test_config_files_that_never_end_are_refused(
    tmp_path: Path, tiny_dataset: Path, capsys
) -> None:
    fifo = tmp_path / "fifo.toml"
    os.mkfifo(fifo)
    big = tmp_path / "big.toml"
    big.write_text("# " + "x" * (2 << 20))
    base = ["train", "--data", str(tiny_dataset), "--out", str(tmp_path / "run")]
    for path, message in (
        ("/dev/zero", "not a regular file"),
        (fifo, "not a regular file"),
        (big, "larger than"),
    ):
        assert main([*base, "--config", str(path)]) == 1
        assert message in capsys.readouterr().err


def test_damaged_training_states_are_refused_before_resuming(
    tmp_path: Path, tiny_dataset: Path, checkpoint: Path, capsys
) -> None:
    torch = pytest.importorskip("torch")
    run = tmp_path / "run"
    args = ["train", "--data", str(tiny_dataset), "--out", str(run), "--device", "cpu"]
    assert main([*args, "--preset", "small", "--width", "0.125", "--epochs", "1"]) == 0
    good = torch.load(run / "last.pt", weights_only=True)
    capsys.readouterr()
    resume = [*args, "--resume", "--epochs", "2"]

    shutil.copy(checkpoint, run / "last.pt")  # a model file where a training state belongs
    assert main(resume) == 1
    assert "is not a training state to resume" in capsys.readouterr().err

    for change, message in (
        (lambda s: s["model"][next(iter(s["model"]))].fill_(float("nan")), "NaN or infinite"),
        (lambda s: s.__setitem__("epoch", 10**12), "impossible epoch"),
        (lambda s: s.__setitem__("rng", {"torch": "not a state"}), "is damaged"),
    ):
        state = {k: (dict(v) if isinstance(v, dict) else v) for k, v in good.items()}
        state["model"] = {k: v.clone() for k, v in good["model"].items()}
        change(state)
        torch.save(state, run / "last.pt")
        assert main(resume) == 1
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err, err


def test_overwrite_keeps_the_users_files_and_follows_a_symlink(tmp_path: Path, capsys) -> None:
    args = ["prepare", "procedural", "--count", "2", "--points", "64", "--overwrite"]
    data = tmp_path / "data"
    assert main([*args, "--out", str(data)]) == 0
    (data / "notes.txt").write_text("mine")
    assert main([*args, "--out", str(data)]) == 1
    assert "holds files pfnet prepare did not write (notes.txt)" in capsys.readouterr().err
    assert (data / "notes.txt").read_text() == "mine"
    # a forged two-key manifest does not make a folder of the user's replaceable
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "manifest.json").write_text('{"format": "pfnet-completion-dataset", "version": 1}')
    (mine / "thesis.tex").write_text("work")
    assert main([*args, "--out", str(mine)]) == 1
    assert (mine / "thesis.tex").read_text() == "work"
    capsys.readouterr()
    # --out through a symbolic link: the folder it names is replaced, the link stays a link
    (data / "notes.txt").unlink()
    link = tmp_path / "link"
    link.symlink_to(data)
    assert main([*args, "--out", str(link), "--seed", "3"]) == 0
    assert link.is_symlink() and (data / "manifest.json").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "link", "mine"]


def test_complete_refuses_names_that_differ_only_in_case(
    tmp_path: Path, checkpoint: Path, capsys
) -> None:
    points = np.random.default_rng(0).normal(size=(300, 3)).astype(np.float32)
    (tmp_path / "a").mkdir()
    write_ply(tmp_path / "scan.ply", points)
    write_ply(tmp_path / "a" / "Scan.ply", points)
    args = ["complete", str(tmp_path / "scan.ply"), str(tmp_path / "a" / "Scan.ply")]
    assert main([*args, "--checkpoint", str(checkpoint), "--out", str(tmp_path / "o")]) == 1
    assert "would both write" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_text_clouds_with_a_byte_order_mark_or_trailing_comments_keep_every_point(
    tmp_path: Path,
) -> None:
    path = tmp_path / "scan.xyz"
    path.write_bytes("\ufeff1 2 3 # first\n4 5 6\n".encode())
    assert read_point_cloud(path).tolist() == [[1, 2, 3], [4, 5, 6]]
    path.write_text("x_m y_m z_m\n1 2 3\n")  # a header may hold underscores
    assert read_point_cloud(path).tolist() == [[1, 2, 3]]
    path.write_text("1_0 2 3\n4 5 6\n")  # a value may not
    with pytest.raises(Exception, match="line 1 is not numeric"):
        read_point_cloud(path)


# ----------------------------------------------------------------------------------------
# The third audit's variants.


def test_predict_gallery_may_not_be_named_as_a_prediction_still_to_come(
    tmp_path: Path, tiny_dataset: Path, checkpoint: Path, capsys
) -> None:
    out = tmp_path / "pred"
    base = ["predict", "--checkpoint", str(checkpoint), "--data", str(tiny_dataset)]
    name = load_name(tiny_dataset)
    for gallery in (out / name, out / "predictions.json"):
        assert main([*base, "--out", str(out), "--device", "cpu", "--gallery", str(gallery)]) == 1
        assert "must be a .png file" in capsys.readouterr().err
    assert not out.exists()
    assert main([*base, "--out", str(out), "--gallery", str(tmp_path / "g.jpg")]) == 1
    assert "must be a .png file" in capsys.readouterr().err


def load_name(data: Path) -> str:
    from pfnet.data import load_split

    test = load_split(data, "test")
    return f"{test.category[0]}/{test.name[0]}.npy"


def test_walked_ply_rows_are_bounded_over_all_elements(tmp_path: Path) -> None:
    from pfnet.errors import DataError

    elements = "".join(
        f"element e{k} 1500000\nproperty list uchar int ids\n" for k in range(3)
    )  # each under the bound, together over it
    header = "ply\nformat binary_little_endian 1.0\n" + elements
    header += "element vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    path = tmp_path / "many.ply"
    path.write_bytes(header.encode() + bytes(4_500_000) + np.zeros(3, "<f4").tobytes())
    with pytest.raises(
        DataError, match="brings the list lengths to read before the vertices to 3000000"
    ):
        read_point_cloud(path)


def test_a_transposed_npy_cloud_is_refused(tmp_path: Path) -> None:
    from pfnet.errors import DataError

    path = tmp_path / "t.npy"
    np.save(path, np.random.default_rng(0).normal(size=(3, 300)).astype(np.float32))
    with pytest.raises(DataError, match=r"is the array transposed"):
        read_point_cloud(path)
    np.save(path, np.random.default_rng(0).normal(size=(300, 7)).astype(np.float32))  # + normals
    assert read_point_cloud(path).shape == (300, 3)
    np.save(path, np.zeros((1000, 100), np.float32))  # features, not points (sixth audit)
    with pytest.raises(DataError, match=r"100 columns of 1000 rows; .*: not points\?"):
        read_point_cloud(path)


def test_an_unreadable_record_gives_a_short_line(
    tmp_path: Path, tiny_dataset: Path, capsys
) -> None:
    pred = write_predictions(tmp_path / "pred", tiny_dataset)
    (pred / "predictions.json").write_bytes(bytes(range(256)) * 4000)  # 1 MB, not UTF-8
    assert main(["evaluate", str(pred), "--data", str(tiny_dataset)]) == 1
    err = capsys.readouterr().err
    assert "cannot read" in err and len(err) < 600
    # one larger than predict ever writes (its list of files included) is not read at all
    with open(pred / "predictions.json", "wb") as record:
        record.truncate(MAX_RECORD_BYTES + 1)  # sparse
    assert main(["evaluate", str(pred), "--data", str(tiny_dataset)]) == 1
    err = capsys.readouterr().err
    assert "predictions.json: larger than 8 MB, not pfnet predict's record" in err


def test_render_refuses_more_rows_than_a_picture_can_show(tmp_path: Path, capsys) -> None:
    cloud = tmp_path / "c.ply"
    write_ply(cloud, np.random.default_rng(0).normal(size=(20, 3)).astype(np.float32))
    assert main(["render", *[str(cloud)] * 201, "--out", str(tmp_path / "x.png")]) == 1
    assert "201 rows is more than the 200" in capsys.readouterr().err


# ----------------------------------------------------------------------------------------
# The fourth audit's variants.


def test_predict_never_follows_a_linked_category_folder_out_of_its_output(
    tmp_path: Path, tiny_dataset: Path, checkpoint: Path, capsys
) -> None:
    from pfnet.data import load_split

    category = str(load_split(tiny_dataset, "test").category[0])
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "keep.npy").write_bytes(b"mine")
    out = tmp_path / "pred"
    out.mkdir()
    (out / category).symlink_to(victim)
    before = _tree(victim)
    args = ["predict", "--checkpoint", str(checkpoint), "--data", str(tiny_dataset)]
    assert main([*args, "--out", str(out), "--device", "cpu"]) == 1
    assert "is a link out of the prediction folder" in capsys.readouterr().err
    assert _tree(victim) == before and sorted(p.name for p in out.iterdir()) == [category]


def test_forged_nesting_in_json_toml_and_config_values_is_one_line(
    tmp_path: Path, tiny_dataset: Path, capsys
) -> None:
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    (data / "manifest.json").write_text("[" * 100000 + "]" * 100000)
    pred = tmp_path / "pred"
    pred.mkdir()
    assert main(["evaluate", str(pred), "--data", str(data)]) == 1
    err = capsys.readouterr().err
    assert "cannot read the manifest" in err and len(err) < 600
    deep = tmp_path / "deep.toml"
    deep.write_text("lr = " + "[" * 50000 + "]" * 50000 + "\n")
    assert (
        main(
            [
                "train",
                "--data",
                str(tiny_dataset),
                "--out",
                str(tmp_path / "r"),
                "--config",
                str(deep),
            ]
        )
        == 1
    )
    err = capsys.readouterr().err
    assert "is not valid TOML" in err and "Traceback" not in err and len(err) < 600
    from pfnet.errors import ConfigError
    from pfnet.training.config import TrainConfig, preset_config

    value: list = []
    for _ in range(80):  # shared references: 2^80 elements when printed in full
        value = [value, value]
    with pytest.raises(ConfigError, match=r"n_points must be .*; got \[\[\[") as caught:
        TrainConfig.from_dict({**preset_config("small").to_dict(), "n_points": value})
    assert len(str(caught.value)) < 400


@pytest.mark.slow  # end to end, or a measurement: runs in CI, not the default run
def test_forged_string_widths_and_category_names_in_a_split(
    tmp_path: Path, tiny_dataset: Path, checkpoint: Path, capsys
) -> None:
    import json

    from pfnet.data import load_split
    from pfnet.errors import DataError

    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    test = load_split(data, "test")
    n = len(test)
    wide = np.array(["x"] * n, dtype="<U100000000")[:0]  # the dtype alone, no memory
    header_only = tmp_path / "wide.npy"
    with open(header_only, "wb") as fh:
        np.lib.format.write_array_header_1_0(
            fh, {"descr": wide.dtype.str, "fortran_order": False, "shape": (n,)}
        )
    import zipfile

    with zipfile.ZipFile(data / "test.npz", "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("points.npy", _npy_bytes(test.points))
        archive.writestr("category.npy", header_only.read_bytes() + bytes(1000))
        archive.writestr("name.npy", _npy_bytes(test.name))
    with pytest.raises(DataError, match="declares strings of 100000000 characters"):
        load_split(data, "test")
    # a forged manifest that lists a category named like predict's record file
    manifest = json.loads((data / "manifest.json").read_text())
    manifest["categories"] = [*manifest["categories"], "predictions.json"]
    category = test.category.copy().astype("<U32")
    counts = manifest["splits"]["test"]["categories"]  # ... and forges the record to agree
    counts[str(category[0])] -= 1
    counts["predictions.json"] = 1
    category[0] = "predictions.json"
    (data / "manifest.json").write_text(json.dumps(manifest))
    np.savez(data / "test.npz", points=test.points, category=category, name=test.name)
    out = tmp_path / "pred"
    args = ["predict", "--checkpoint", str(checkpoint), "--data", str(data), "--out", str(out)]
    assert main([*args, "--device", "cpu"]) == 1
    err = capsys.readouterr().err
    assert "category 'predictions.json' is the name of the record predict writes" in err
    assert not out.exists()


def _npy_bytes(array: np.ndarray) -> bytes:
    import io

    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def test_render_draws_huge_clouds_thinned_and_ascii_ply_lines_are_bounded(tmp_path: Path) -> None:
    from pfnet.errors import DataError
    from pfnet.viz.rendering import MAX_DRAWN, RenderSample, render_gallery

    big = np.random.default_rng(0).normal(size=(MAX_DRAWN * 20, 3)).astype(np.float32)
    path = render_gallery(tmp_path / "big.png", [RenderSample("big", big)], views=1)
    assert path.stat().st_size > 0
    header = "ply\nformat ascii 1.0\nelement junk 30000000\nproperty float a\n"
    header += "element vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    ply = tmp_path / "lines.ply"
    ply.write_text(header + "1\n" * 10)
    with pytest.raises(DataError, match="ASCII PLY declares 30000001 lines"):
        read_point_cloud(ply)


# ----------------------------------------------------------------------------------------
# The fifth audit's variants.


def test_publish_writes_only_plain_names_into_real_folders(tmp_path: Path) -> None:
    import json

    from pfnet.errors import DataError
    from pfnet.study import publish

    out = tmp_path / "results"
    (out / "runs" / "ok").mkdir(parents=True)
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "config.json").write_text("mine")
    for name in ("config.json", "log.jsonl", "eval-missing.json", "eval-whole.json"):
        (out / "runs" / "ok" / name).write_text("{}")
    for name, message in (("../../victim", "not allowed in a file name"), ("..", "is not a name")):
        (out / "results.json").write_text(json.dumps({"runs": [{"name": name}]}))
        with pytest.raises(DataError, match=message):
            publish(out, tmp_path / "pub")
    assert (victim / "config.json").read_text() == "mine"
    (out / "results.json").write_text(json.dumps({"runs": [{"name": "ok"}]}))
    pub = tmp_path / "pub2"
    (pub / "runs" / "ok").mkdir(parents=True)
    (pub / "runs" / "ok" / "config.json").symlink_to(victim / "config.json")  # a planted file link
    publish(out, pub)
    assert (victim / "config.json").read_text() == "mine"  # replaced the link, not its target
    assert not (pub / "runs" / "ok" / "config.json").is_symlink()
    linked = tmp_path / "pub3"
    linked.mkdir()
    (linked / "runs").symlink_to(victim)
    with pytest.raises(DataError, match="is a link"):
        publish(out, linked)


def test_demo_refuses_a_planted_link_among_its_folders(tmp_path: Path, capsys) -> None:
    pytest.importorskip("torch")
    out = tmp_path / "demo"
    out.mkdir()
    victim = tmp_path / "victim"
    victim.mkdir()
    (out / "predictions").symlink_to(victim)
    args = ["demo", "--out", str(out), "--procedural", "--count", "3", "--points", "512"]
    assert main([*args, "--epochs", "1"]) == 1
    assert "is a link; the demo writes only into real folders" in capsys.readouterr().err
    assert list(victim.iterdir()) == []


def test_checkpoint_tables_with_other_than_plain_tensors_are_one_line(
    tmp_path: Path, checkpoint: Path, capsys
) -> None:
    torch = pytest.importorskip("torch")
    state = torch.load(checkpoint, weights_only=True)
    scan = tmp_path / "s.ply"
    write_ply(scan, np.random.default_rng(0).normal(size=(300, 3)).astype(np.float32))
    first = next(iter(state["model"]))
    for label, value, message in (
        ("int", 1, "is not a plain tensor"),
        ("sparse", state["model"][first].to_sparse(), "cannot be read"),  # torch refuses it
    ):
        forged = {**state, "model": {**state["model"], first: value}}
        path = tmp_path / f"{label}.pt"
        torch.save(forged, path)
        assert (
            main(["complete", str(scan), "--checkpoint", str(path), "--out", str(tmp_path / "o")])
            == 1
        )
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err and len(err.splitlines()) == 1


def test_manifests_with_odd_split_records_and_forged_member_dtypes(
    tmp_path: Path, tiny_dataset: Path
) -> None:
    import json

    from pfnet.data import load_split
    from pfnet.errors import DataError

    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    manifest = json.loads((data / "manifest.json").read_text())
    # a record that is there must be whole and true (the sixth audit: these were accepted,
    # and the split then went unchecked); a manifest with no "splits" at all is an early one
    test_record = manifest["splits"]["test"]
    wrong_count = {**test_record, "categories": {"chair": test_record["total"]}}
    for splits in (
        "x",
        [1],
        None,
        {"test": "x"},
        {"test": {"categories": "x"}},
        {"test": {"count": "x"}},
        {"test": {"total": True, "categories": {}}},
        {"test": {**test_record, "total": test_record["total"] + 1}},
    ):
        (data / "manifest.json").write_text(json.dumps({**manifest, "splits": splits}))
        with pytest.raises(DataError, match="record of the test split is malformed"):
            load_split(data, "test")
    assert len(test_record["categories"]) > 1  # so that all-chairs is a wrong count
    splits = {**manifest["splits"], "test": wrong_count}
    (data / "manifest.json").write_text(json.dumps({**manifest, "splits": splits}))
    with pytest.raises(DataError, match="shapes per category differ from the manifest"):
        load_split(data, "test")
    (data / "manifest.json").write_text(
        json.dumps({k: v for k, v in manifest.items() if k != "splits"})
    )
    assert len(load_split(data, "test")) > 0  # no record to compare with: still readable
    (data / "manifest.json").write_text(json.dumps(manifest))
    test = load_split(data, "test")
    for member, array, message in (
        ("category.npy", np.zeros(len(test), dtype="|S700"), "declares strings of 700 characters"),
        ("points.npy", np.zeros((len(test), 512, 4), np.float32), r"has points of shape \(4,\)"),
    ):
        arrays = {"points": test.points, "category": test.category, "name": test.name}
        arrays[member[:-4]] = array
        np.savez(data / "test.npz", **arrays)
        with pytest.raises(DataError, match=message):
            load_split(data, "test")


def test_a_missing_torch_is_one_line_and_other_missing_modules_stay_visible(
    monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    import pfnet.commands.models

    def needs(name):
        def run(_args):
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)

        return run

    monkeypatch.setattr(pfnet.commands.models, "run", needs("torch"))
    assert main(["models"]) == 1
    assert "needs PyTorch, which is not installed: pip install torch" in capsys.readouterr().err
    monkeypatch.setattr(pfnet.commands.models, "run", needs("pfnet.nothing"))
    with pytest.raises(ModuleNotFoundError):
        main(["models"])


# ----------------------------------------------------------------------------------------
# The sixth audit's variants (a study's forged results).

RESULTS = Path(__file__).resolve().parents[2] / "results" / "study"


@pytest.mark.skipif(not (RESULTS / "results.json").is_file(), reason="no published results")
def test_forged_study_records_are_one_line_and_publish_nothing_half_way(
    tmp_path: Path, capsys
) -> None:
    import json

    out = tmp_path / "results"
    shutil.copytree(RESULTS, out)
    record = json.loads((out / "results.json").read_text())
    forged = json.loads(json.dumps(record))
    forged["settings"][0]["model"] = "zzz"
    (out / "results.json").write_text(json.dumps(forged))
    assert main(["reproduce", "--out", str(out), "--report-only"]) == 1
    err = capsys.readouterr().err
    assert "is not a study record this pfnet can report" in err and "Traceback" not in err
    forged = json.loads(json.dumps(record))
    forged["runs"][0]["name"] = 5
    (out / "results.json").write_text(json.dumps(forged))
    pub = tmp_path / "pub"
    assert main(["reproduce", "--out", str(out), "--report-only", "--publish", str(pub)]) == 1
    assert not pub.exists()
    capsys.readouterr()


# ----------------------------------------------------------------------------------------
# The sixth audit's variants.


def test_predict_gallery_may_not_be_a_category_folder_to_come_or_inside_one(
    tmp_path: Path, tiny_dataset: Path, checkpoint: Path, capsys
) -> None:
    """A category named like the gallery made predict write every prediction, then fail on
    the gallery; the check now knows the category folders before anything is written."""
    import json
    import shutil

    from pfnet.data import load_split

    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    test = load_split(data, "test")
    category = np.where(test.category == "chair", "gallery.png", test.category)
    np.savez(data / "test.npz", points=test.points, category=category, name=test.name)
    manifest = json.loads((data / "manifest.json").read_text())
    manifest["categories"] = [*manifest["categories"], "gallery.png"]
    record = manifest["splits"]["test"]["categories"]
    record["gallery.png"] = record.pop("chair")
    (data / "manifest.json").write_text(json.dumps(manifest))
    out = tmp_path / "pred"
    base = ["predict", "--checkpoint", str(checkpoint), "--data", str(data), "--out", str(out)]
    for gallery, message in (
        (out / "gallery.png", "would overwrite a file of the prediction folder"),
        (out / "lamp" / "g.png", "inside a subfolder of the prediction folder"),
        (out / "new" / "g.png", "inside a subfolder of the prediction folder"),
    ):
        assert main([*base, "--device", "cpu", "--gallery", str(gallery)]) == 1
        err = capsys.readouterr().err
        assert message in err and len(err.splitlines()) == 1, err
        assert not out.exists()
    # "new/../g.png" is the folder itself: accepted, and no empty "new" is left behind
    assert main([*base, "--device", "cpu", "--gallery", f"{out}/new/../g.png"]) == 0
    assert (out / "g.png").is_file() and not (out / "new").exists()
