"""The tenth hostile audit's protocol findings: a benchmark protocol run on a data set it does
not define (a ShapeNet-55 number from 512-point clouds), a NaN ``--missing-ratio``, PyTorch's
``weights_only=False`` advice relayed for an unreadable checkpoint, a manifest larger than its
own reader accepts, and ``predict --out`` writing into a data set or another run's folder."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from pfnet.checkpoint import read_checkpoint  # noqa: E402
from pfnet.cli import main  # noqa: E402
from pfnet.errors import DataError  # noqa: E402


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
    import numpy as np

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
    from pfnet.evaluation import evaluate_benchmark
    from pfnet.protocols import check_protocol_data, get_protocol

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
    from pfnet.checkpoint import save_checkpoint
    from pfnet.models import build_model
    from pfnet.training.config import preset_config

    config = preset_config("small").replace(n_points=n_points, width=0.125)
    torch.manual_seed(0)
    save_checkpoint(path, {"config": config.to_dict(), "model": build_model(config).state_dict()})
    return path


def test_predict_refuses_another_runs_folder_unless_overwrite(tiny_dataset, tmp_path, capsys):
    import json

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
    assert "holds files pfnet predict did not write (notes.txt)" in capsys.readouterr().err
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
    for name in (".pfnet-replaced-mine", "emptyuser", "mine", category.name):
        planted = sorted(str(p.relative_to(out)) for p in out.rglob("*"))
        assert main([*args, "--split", "test", "--overwrite"]) == 1
        assert f"holds files pfnet predict did not write ({name}" in capsys.readouterr().err
        assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == planted
        victim = out / name if name != category.name else category / ".x.npy"
        (shutil.rmtree if victim.is_dir() else Path.unlink)(victim)
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == before
    # a record that does not name its categories (older pfnet) is not replaced
    record = json.loads((out / "predictions.json").read_text())
    del record["categories"]
    (out / "predictions.json").write_text(json.dumps(record))
    assert main([*args, "--split", "test", "--overwrite"]) == 1
    assert "does not name its categories (an older pfnet wrote it)" in capsys.readouterr().err
    # an unreadable record is not replaced
    (out / "predictions.json").write_text("{not json")
    assert main([*args, "--split", "test", "--overwrite"]) == 1
    assert "predictions.json cannot be read, so it is not a folder" in capsys.readouterr().err


def test_predict_again_removes_the_leftover_of_an_interrupted_replacement(tiny_dataset, tmp_path):
    """Audit 11 (N8): a same-run predict left the hidden folder of an interrupted overwrite."""
    checkpoint = _small_checkpoint(tmp_path / "m.pt", 512)
    out = tmp_path / "pred"
    args = ["predict", "--checkpoint", str(checkpoint), "--data", str(tiny_dataset)]
    args += ["--out", str(out), "--device", "cpu"]
    assert main(args) == 0
    leftover = out / ".pfnet-replaced-0123456789ab" / "chair" / "old.npy"
    lookalike = out / ".pfnet-replaced-mine" / "chair" / "mine.npy"
    for path in (leftover, lookalike):
        path.parent.mkdir(parents=True)
        path.write_bytes(b"x")
    assert main(args) == 0
    assert not leftover.parent.parent.exists() and lookalike.read_bytes() == b"x"
