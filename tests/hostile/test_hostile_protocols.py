"""The tenth hostile audit's protocol findings: a benchmark protocol run on a data set it does
not define (a ShapeNet-55 number from 512-point clouds), a NaN ``--missing-ratio``, PyTorch's
``weights_only=False`` advice relayed for an unreadable checkpoint, a manifest larger than its
own reader accepts, and ``predict --out`` writing into a data set or another run's folder."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from pfnet.cli import main  # noqa: E402
from pfnet.errors import DataError  # noqa: E402
from pfnet.inference.checkpoint import read_checkpoint  # noqa: E402


class Foreign:
    """A class a weights-only load refuses to unpickle."""


def test_unreadable_checkpoint_never_relays_weights_only_advice(tmp_path, capsys):
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"garbage\n")
    foreign = tmp_path / "foreign.pt"
    torch.save({"x": Foreign()}, foreign)
    for path in (junk, foreign):
        with pytest.raises(DataError, match="cannot be read: not a pfnet checkpoint") as err:
            read_checkpoint(path)
        assert "weights_only" not in str(err.value)
        assert "never unpickles code" in str(err.value)
    onnx = tmp_path / "m.onnx"
    onnx.write_bytes(b"\x08\x07garbage")
    with pytest.raises(DataError, match=r"m\.onnx cannot be read: it is an ONNX model"):
        read_checkpoint(onnx)
    out = tmp_path / "o"
    args = ["predict", "--checkpoint", str(junk), "--data", str(tmp_path), "--out", str(out)]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "weights_only" not in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("ratio", ["nan", "inf", "0", "1", "0.3"])
def test_evaluate_shapenet55_refuses_a_ratio_it_does_not_define(tmp_path, ratio, capsys):
    pred = tmp_path / "pred"
    pred.mkdir()
    args = ["evaluate", str(pred), "--data", str(tmp_path), "--protocol", "shapenet55"]
    assert main([*args, "--missing-ratio", ratio]) == 1
    err = capsys.readouterr().err
    if ratio == "0.3":
        assert "--missing-ratio of the shapenet55 protocol is one of 0.25, 0.5, 0.75" in err
    else:
        assert f"--missing-ratio must be in (0, 1), got {float(ratio)}" in err


def test_prepare_lists_at_most_a_thousand_skipped_files(tmp_path, capsys):
    from pfnet.data.format import MAX_SKIPPED_LISTED, read_manifest

    root = tmp_path / "ShapeNet55-34"
    (root / "shapenet_pc").mkdir(parents=True)
    rng = np.random.default_rng(0)
    files = []
    for k in range(4):
        name = f"02691156-m{k}.npy"
        np.save(root / "shapenet_pc" / name, rng.normal(size=(8192, 3)).astype(np.float32))
        files.append(name)
    missing = [f"02691156-missing{i}{'x' * 200}.npy" for i in range(3000)]
    (root / "ShapeNet-55").mkdir()
    (root / "ShapeNet-55" / "train.txt").write_text("\n".join(files[:2] + missing) + "\n")
    (root / "ShapeNet-55" / "test.txt").write_text("\n".join(files[2:]) + "\n")
    out = tmp_path / "data"
    assert main(["prepare", str(root), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "skipped 3000 files:" in printed and "… and 2980 more" in printed
    assert len(printed.splitlines()) < 100
    manifest = read_manifest(out)
    assert len(manifest["skipped"]) == MAX_SKIPPED_LISTED
    assert manifest["skipped_not_listed"] == 3000 - MAX_SKIPPED_LISTED
    assert all(len(s["path"]) <= 300 for s in manifest["skipped"])
    assert (out / "manifest.json").stat().st_size < 1 << 20
    assert main(["prepare", str(root), "--out", str(out), "--overwrite"]) == 0


@pytest.mark.parametrize("protocol", ["shapenet55", "pcn", "kitti"])
def test_a_benchmark_protocol_refuses_a_data_set_it_does_not_define(
    tiny_dataset, tmp_path, protocol, capsys
):
    from pfnet.evaluation.benchmarks import evaluate_benchmark
    from pfnet.evaluation.protocols import check_protocol_data, get_protocol

    want = f"the {protocol} protocol needs a data set prepared from its benchmark, but"
    with pytest.raises(DataError, match=want) as err:
        check_protocol_data(get_protocol(protocol), tiny_dataset)
    assert "is a procedural data set of 512 points a cloud" in str(err.value)
    pred = tmp_path / "pred"
    pred.mkdir()
    if protocol != "kitti":
        with pytest.raises(DataError, match=want):
            evaluate_benchmark(pred, tiny_dataset, protocol)
    checkpoint = tmp_path / "model.pt"
    checkpoint.write_bytes(b"not read before the data set is checked")
    args = ["--data", str(tiny_dataset), "--protocol", protocol]
    out = tmp_path / "o"
    assert main(["predict", "--checkpoint", str(checkpoint), "--out", str(out), *args]) == 1
    assert want in capsys.readouterr().err
    assert not out.exists() or not any(out.iterdir())


def test_predict_refuses_a_data_set_as_its_out_folder(tiny_dataset, tmp_path, capsys):
    args = ["predict", "--checkpoint", str(tmp_path / "m.pt"), "--data", str(tmp_path)]
    assert main([*args, "--out", str(tiny_dataset)]) == 1
    assert f"--out {tiny_dataset} is a prepared data set" in capsys.readouterr().err


def _small_checkpoint(path, n_points: int):
    from pfnet.inference.checkpoint import save_checkpoint
    from pfnet.models import build_model
    from pfnet.training.config import preset_config

    config = preset_config("small").replace(n_points=n_points, width=0.125)
    torch.manual_seed(0)
    save_checkpoint(path, {"config": config.to_dict(), "model": build_model(config).state_dict()})
    return path


def test_predict_refuses_another_runs_folder_unless_overwrite(tiny_dataset, tmp_path, capsys):
    from pfnet.data import load_split

    checkpoint = _small_checkpoint(tmp_path / "m.pt", 512)
    out = tmp_path / "pred"
    args = ["predict", "--checkpoint", str(checkpoint), "--data", str(tiny_dataset)]
    args += ["--out", str(out), "--device", "cpu"]
    assert main([*args, "--split", "test"]) == 0
    assert main([*args, "--split", "test", "--missing-ratio", "0.5"]) == 0  # the same run
    test_files = sorted(out.glob("*/*.npy"))
    # another split: refused, nothing changed
    assert main([*args, "--split", "val"]) == 1
    err = capsys.readouterr().err
    assert f"{out} holds the predictions of another run (data {tiny_dataset}" in err
    assert "split test, protocol test); pass --overwrite to replace them" in err
    assert sorted(out.glob("*/*.npy")) == test_files
    assert json.loads((out / "predictions.json").read_text())["split"] == "test"
    # --overwrite replaces only what pfnet predict wrote
    (out / "notes.txt").write_text("mine")
    assert main([*args, "--split", "val", "--overwrite"]) == 1
    assert "holds files its predictions.json does not list (notes.txt)" in capsys.readouterr().err
    assert (out / "notes.txt").read_text() == "mine"
    (out / "notes.txt").unlink()
    assert main([*args, "--split", "val", "--overwrite"]) == 0
    val = load_split(tiny_dataset, "val")
    want = sorted(f"{c}/{n}.npy" for c, n in zip(val.category, val.name, strict=True))
    assert sorted(str(p.relative_to(out)) for p in out.glob("*/*.npy")) == want
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == []
    assert json.loads((out / "predictions.json").read_text())["split"] == "val"
    # audit 11: folders the record does not name, hidden files and look-alike leftovers are
    # the user's; --overwrite refuses them and deletes nothing
    before = sorted(str(p.relative_to(out)) for p in out.rglob("*"))
    for planted in ("mine/my_scan.npy", ".pfnet-replaced-mine/chair/a.npy"):
        (out / planted).parent.mkdir(parents=True)
        (out / planted).write_bytes(b"mine")
    (out / "emptyuser").mkdir()
    category = max(p for p in out.iterdir() if p.is_dir() and p.name > "mine")  # named last
    (category / ".x.npy").write_bytes(b"mine")
    for name in (".pfnet-replaced-mine", "emptyuser", "mine", f"{category.name}/.x.npy"):
        planted = sorted(str(p.relative_to(out)) for p in out.rglob("*"))
        assert main([*args, "--split", "test", "--overwrite"]) == 1
        err = capsys.readouterr().err
        assert f"holds files its predictions.json does not list ({name}" in err
        assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == planted
        (shutil.rmtree if (out / name).is_dir() else Path.unlink)(out / name)
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == before
    # a record that does not list its files (the previous release's, which named only its
    # categories; older ones not even those) is not replaced: which files are its is not known
    record = json.loads((out / "predictions.json").read_text())
    del record["files"]
    for named, shown in (
        (True, "remove them yourself (it names the category folders chair, lamp, sofa, ...) or"),
        (False, "remove them yourself or choose"),
    ):
        if not named:
            del record["categories"]
        (out / "predictions.json").write_text(json.dumps(record))
        assert main([*args, "--split", "test", "--overwrite"]) == 1
        err = capsys.readouterr().err
        assert "its predictions.json does not list the files of its predictions (older" in err
        assert shown in err
        assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == before
    # an unreadable record is not replaced
    (out / "predictions.json").write_text("{not json")
    assert main([*args, "--split", "test", "--overwrite"]) == 1
    assert "predictions.json cannot be read, so it is not a folder" in capsys.readouterr().err


def _predict_args(tiny_dataset, tmp_path):
    checkpoint = _small_checkpoint(tmp_path / "m.pt", 512)
    out = tmp_path / "pred"
    args = ["predict", "--checkpoint", str(checkpoint), "--data", str(tiny_dataset)]
    return out, [*args, "--out", str(out), "--device", "cpu"]


def _tree(folder: Path) -> dict[str, bytes | None]:
    """Every path under ``folder`` with its bytes (None for a folder)."""
    return {
        str(p.relative_to(folder)): None if p.is_dir() else p.read_bytes()
        for p in sorted(folder.rglob("*"))
    }


def _split_files(tiny_dataset, split: str) -> list[str]:
    from pfnet.data import load_split

    clouds = load_split(tiny_dataset, split)
    return sorted(f"{c}/{n}.npy" for c, n in zip(clouds.category, clouds.name, strict=True))


def test_overwrite_keeps_a_file_of_yours_in_a_recorded_category_folder(
    tiny_dataset, tmp_path, capsys
):
    """Audit P3: --overwrite deleted a user's .npy inside a category folder the old record
    named, taking every .npy there for the old run's; the record now lists its files."""
    out, args = _predict_args(tiny_dataset, tmp_path)
    assert main([*args, "--split", "test"]) == 0
    record = json.loads((out / "predictions.json").read_text())
    names: dict[str, list[str]] = {}
    for file in _split_files(tiny_dataset, "test"):
        category, name = file[:-4].split("/")
        names.setdefault(category, []).append(name)
    assert record["files"] == {"endings": [".npy"], "names": names}
    np.save(out / "chair" / "my_scan.npy", np.ones((5, 3), np.float32))
    before = _tree(out)
    assert main([*args, "--split", "val", "--overwrite"]) == 1
    assert capsys.readouterr().err == (
        f"pfnet predict: error: {out} holds files its predictions.json does not list "
        "(chair/my_scan.npy); --overwrite replaces only a folder of nothing but the listed "
        "files, so move these out first or choose another prediction folder\n"
    )
    assert _tree(out) == before
    (out / "chair" / "my_scan.npy").unlink()
    # an interrupted write of a listed file is the run's; one of another name, and a listed
    # name that is a link (to a file of the user's), are not
    first, second = _split_files(tiny_dataset, "test")[:2]
    category, name = first[:-4].split("/")
    interrupted = out / category / f".{name}.0123456789ab.tmp.npy"
    interrupted.write_bytes(b"x")
    mine = tmp_path / "mine.npy"
    mine.write_bytes(b"mine")
    stranger, linked = out / category / ".my_scan.0123456789ab.tmp.npy", out / second
    linked.unlink()
    for path in (stranger, linked):
        if path == linked:
            path.symlink_to(mine)
        else:
            path.write_bytes(b"mine")
        before = _tree(out)
        assert main([*args, "--split", "val", "--overwrite"]) == 1
        shown = path.relative_to(out)
        assert f"does not list ({shown}); --overwrite" in capsys.readouterr().err
        assert _tree(out) == before
        path.unlink()
    assert main([*args, "--split", "val", "--overwrite"]) == 0
    assert sorted(str(p.relative_to(out)) for p in out.glob("*/*")) == _split_files(
        tiny_dataset, "val"
    )
    assert not interrupted.exists() and mine.read_bytes() == b"mine"


def test_a_forged_record_removes_no_file_it_does_not_list(tiny_dataset, tmp_path, capsys):
    """A record naming a folder of the user's deleted it: its category list was trusted alone.
    Now only the files it lists go, and only from a folder of nothing else."""
    out, args = _predict_args(tiny_dataset, tmp_path)
    assert main([*args, "--split", "test"]) == 0
    (out / "mine").mkdir()
    (out / "mine" / "scan.npy").write_bytes(b"mine")
    record = json.loads((out / "predictions.json").read_text())
    before = _tree(out)
    record["categories"].append("mine")
    forged = [
        # the folder named among the files, the user's file not
        ({"endings": [".npy"], "names": {**record["files"]["names"], "mine": ["other"]}}, True),
        # the folder named among the categories alone (the rule the previous release had)
        (record["files"], True),
        # no listing: endings that are no prediction's, too many, names not lists of names
        ({"endings": [""], "names": {"mine": ["scan.npy"]}}, False),
        ({"endings": [".txt"], "names": {"mine": ["scan"]}}, False),
        ({"endings": [".npy"] * 9, "names": {"mine": ["scan"]}}, False),
        ({"endings": [".npy"], "names": {"mine": "scan"}}, False),
        ({"endings": ".npy", "names": {"mine": ["scan"]}}, False),
        (["mine/scan.npy"], False),
    ]
    for files, listing in forged:
        (out / "predictions.json").write_text(json.dumps({**record, "files": files}))
        before["predictions.json"] = (out / "predictions.json").read_bytes()
        assert main([*args, "--split", "val", "--overwrite"]) == 1
        err = capsys.readouterr().err
        if listing:
            assert "holds files its predictions.json does not list (mine" in err
        else:
            assert "does not list the files of its predictions" in err
            assert "yourself (it names the category folders chair, lamp, mine, ...) or" in err
        assert _tree(out) == before


def test_an_interrupted_overwrite_is_finished_by_the_next(
    tiny_dataset, tmp_path, capsys, monkeypatch
):
    """Stopped while removing the old run's files, --overwrite leaves the old record, which
    lists those left, and the next --overwrite finishes; nothing hidden is left behind (audit
    11, N8: the hidden folder an interrupted replacement left). Such a folder left by the
    previous release lists no files: it is kept, and --overwrite names it."""
    out, args = _predict_args(tiny_dataset, tmp_path)
    assert main([*args, "--split", "test"]) == 0
    removed: list[Path] = []
    unlink = Path.unlink

    def interrupted(self, missing_ok=False):
        removed.append(self)
        if len(removed) == 3:
            raise KeyboardInterrupt
        unlink(self, missing_ok=missing_ok)

    monkeypatch.setattr(Path, "unlink", interrupted)
    assert main([*args, "--split", "val", "--overwrite"]) == 130
    monkeypatch.undo()
    capsys.readouterr()
    assert json.loads((out / "predictions.json").read_text())["split"] == "test"
    left = sorted(str(p.relative_to(out)) for p in out.glob("*/*"))
    assert left == [f for f in _split_files(tiny_dataset, "test") if out / f not in removed[:2]]
    assert len(left) == len(_split_files(tiny_dataset, "test")) - 2
    assert main([*args, "--split", "val", "--overwrite"]) == 0
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*.npy")) == _split_files(
        tiny_dataset, "val"
    )
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == []
    # the previous release's leftover: a same-run predict keeps it, --overwrite names it
    leftover = out / ".pfnet-replaced-0123456789ab" / "chair" / "old.npy"
    leftover.parent.mkdir(parents=True)
    leftover.write_bytes(b"x")
    assert main([*args, "--split", "val"]) == 0
    assert leftover.read_bytes() == b"x"
    assert main([*args, "--split", "test", "--overwrite"]) == 1
    err = capsys.readouterr().err
    assert "does not list (.pfnet-replaced-0123456789ab); --overwrite" in err
    assert leftover.read_bytes() == b"x"


def test_a_file_put_in_a_folder_being_replaced_after_its_check_is_kept(tiny_dataset, tmp_path):
    """Between the check (before the model runs) and the removal a file may appear: only the
    listed files go, the folder stays with the file, and the old record with them."""
    from pfnet.evaluation.prediction_folder import check_prediction_folder, open_prediction_folder
    from pfnet.evaluation.prediction_record import run_files

    out, args = _predict_args(tiny_dataset, tmp_path)
    assert main([*args, "--split", "test"]) == 0
    replaced = check_prediction_folder(out, tiny_dataset, "val", "test", overwrite=True)
    (out / "lamp" / "late.npy").write_bytes(b"mine")
    with pytest.raises(
        DataError,
        match=r"pred holds files its predictions.json does not list "
        r"\(lamp/late.npy\); --overwrite replaces only",
    ):
        open_prediction_folder(
            out,
            run_files(["chair"], ["a"]),
            "val",
            {"name": "test"},
            data_dir=tiny_dataset,
            replaced=replaced,
        )
    assert (out / "lamp" / "late.npy").read_bytes() == b"mine"
    assert json.loads((out / "predictions.json").read_text())["split"] == "test"


def test_a_run_too_large_to_list_its_files_is_not_overwritten(
    tiny_dataset, tmp_path, capsys, monkeypatch
):
    """A record stays within MAX_RECORD_BYTES (its readers' bound): a run whose list of files
    would not fit records none, and --overwrite refuses its folder as an older record's."""
    from pfnet.evaluation import prediction_record

    out, args = _predict_args(tiny_dataset, tmp_path)
    assert main([*args, "--split", "test"]) == 0
    record = json.loads((out / "predictions.json").read_text())
    bound = len(json.dumps({**record, "files": None}, indent=2)) + 100
    assert (out / "predictions.json").stat().st_size > bound
    monkeypatch.setattr(prediction_record, "MAX_RECORD_BYTES", bound)
    shutil.rmtree(out)
    assert main([*args, "--split", "test"]) == 0
    assert (out / "predictions.json").stat().st_size <= bound
    assert json.loads((out / "predictions.json").read_text())["files"] is None
    assert main(["evaluate", str(out), "--data", str(tiny_dataset)]) == 0
    before = _tree(out)
    assert main([*args, "--split", "val", "--overwrite"]) == 1
    err = capsys.readouterr().err
    assert (
        "does not list the files of its predictions (older pfnet versions, and runs of more" in err
    )
    assert _tree(out) == before
    # a record larger than the bound cannot be read
    monkeypatch.setattr(prediction_record, "MAX_RECORD_BYTES", 100)
    assert main([*args, "--split", "val", "--overwrite"]) == 1
    assert "predictions.json cannot be read, so it is not a folder" in capsys.readouterr().err
    assert _tree(out) == before
