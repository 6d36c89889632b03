"""Two runs at once, and files pfnet did not write (issue 36, classes 3 and 4).

Every command that writes a folder holds an exclusive flock on it, every command that reads
one another may rewrite a shared one (:mod:`pfnet.io.locks`); the other is refused naming the
folder and the process. The holders here are other processes, as a second run would be.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pfnet.cli import main
from pfnet.data import load_split
from pfnet.data.digests import loaded_split_digest
from pfnet.data.format import write_dataset
from pfnet.data.temporaries import TEMPORARY_MARK
from pfnet.errors import DataError
from pfnet.io.locks import folder_lock, holders

HOLD = (
    "import sys, time; from pfnet.io.locks import folder_lock\n"
    "with folder_lock(sys.argv[1], 'holding', shared=sys.argv[2] == 'shared'):\n"
    "    print('held', flush=True); time.sleep(120)\n"
)


class Holder:
    """Another process holding ``folder`` (exclusive, or shared) until the block ends."""

    def __init__(self, folder: Path, *, shared: bool = False) -> None:
        self.folder, self.shared = folder, shared

    def __enter__(self) -> subprocess.Popen:
        mode = "shared" if self.shared else "exclusive"
        self.process = subprocess.Popen(
            [sys.executable, "-c", HOLD, str(self.folder), mode], stdout=subprocess.PIPE, text=True
        )
        assert self.process.stdout.readline() == "held\n"
        return self.process

    def __exit__(self, *exc) -> None:
        self.process.kill()
        self.process.communicate()


def _tries(folder: Path, *, shared: bool = False) -> str:
    """What another process is told when it tries to take ``folder`` now."""
    script = (
        "import sys; from pfnet.io.locks import folder_lock; from pfnet.errors import DataError\n"
        "try:\n"
        "    with folder_lock(sys.argv[1], 'trying', shared=sys.argv[2] == 'shared'):\n"
        "        print('took')\n"
        "except DataError as err:\n"
        "    print(err)\n"
    )
    mode = "shared" if shared else "exclusive"
    done = subprocess.run(
        [sys.executable, "-c", script, str(folder), mode], capture_output=True, text=True
    )
    return done.stdout


def test_a_held_folder_is_refused_naming_the_process(tmp_path):
    with Holder(tmp_path) as other:
        assert holders(tmp_path)[0][0] == other.pid
        with pytest.raises(DataError) as err:
            with folder_lock(tmp_path, "writing into"):
                pass
    message = str(err.value)
    assert (
        f"cannot start writing into {tmp_path}: it is in use by pid {other.pid} (-c import"
        in message
    )
    with folder_lock(tmp_path, "writing into"):  # the kernel let go when it died
        pass
    assert list(tmp_path.iterdir()) == []  # no lock file left in the user's folder


def test_readers_share_and_keep_writers_out(tmp_path):
    with Holder(tmp_path, shared=True) as other:
        assert _tries(tmp_path, shared=True) == "took\n"
        assert f"in use by pid {other.pid}" in _tries(tmp_path)


def test_train_holds_its_run_folder_and_a_second_run_is_refused(tiny_dataset, tmp_path, capsys):
    pytest.importorskip("torch")
    from pfnet.training import loop

    run = tmp_path / "run"
    told = []
    real_run = loop.Trainer.run

    def run_and_look(self, *args, **kwargs):
        told.append(_tries(run))  # another process, while this run trains
        return real_run(self, *args, **kwargs)

    argv = ["train", "--data", str(tiny_dataset), "--out", str(run), "--preset", "small"]
    argv += ["--model", "mlp", "--epochs", "1", "--batch-size", "8", "--width", "0.125"]
    loop.Trainer.run = run_and_look
    try:
        assert main(argv) == 0
    finally:
        loop.Trainer.run = real_run
    assert f"trying {run}: it is in use by pid {os.getpid()}" in told[0]
    before = {p.name: p.stat().st_mtime_ns for p in run.iterdir()}
    with Holder(run) as other:  # a run still going: --resume is refused, nothing written
        capsys.readouterr()
        assert main([*argv[:5], "--resume"]) == 1
        assert f"in use by pid {other.pid}" in capsys.readouterr().err
        assert main(argv) == 1
    assert {p.name: p.stat().st_mtime_ns for p in run.iterdir()} == before


def test_a_refused_new_run_leaves_no_folder(tiny_dataset, tmp_path):
    pytest.importorskip("torch")
    from pfnet.training.config import TrainConfig
    from pfnet.training.loop import train

    with pytest.raises(DataError, match="last.pt does not exist"):
        train(TrainConfig(), tiny_dataset, tmp_path / "new", device="cpu", resume=True)
    assert not (tmp_path / "new").exists()


def test_complete_into_a_folder_in_use_is_refused(tmp_path, capsys):
    np.savetxt(tmp_path / "scan.xyz", np.random.default_rng(0).random((2000, 3)))
    out = tmp_path / "out"
    out.mkdir()
    with Holder(out) as other:
        assert main(["complete", str(tmp_path / "scan.xyz"), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert f"writing completions into {out}: it is in use by pid {other.pid}" in err
    assert list(out.iterdir()) == []


def test_prepare_overwrite_while_predict_reads_the_data_is_refused(tiny_dataset, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    clouds = load_split(data, "test")
    with Holder(data, shared=True) as other:  # a predict or evaluate reading it
        with pytest.raises(
            DataError, match=rf"cannot start replacing .*data: it is in use by pid {other.pid}"
        ):
            write_dataset(data, {s: load_split(data, s) for s in ("train", "val", "test")}, {},
                          overwrite=True)  # fmt: skip
    np.testing.assert_array_equal(load_split(data, "test").points, clouds.points)


def test_predict_refuses_a_data_set_being_replaced(tiny_dataset, tmp_path, capsys):
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    with Holder(data) as other:  # prepare --overwrite replacing it
        assert main(["predict", "--data", str(data), "--out", str(tmp_path / "p")]) == 1
    assert f"in use by pid {other.pid}" in capsys.readouterr().err
    assert not (tmp_path / "p").exists()


def test_evaluate_refuses_a_prediction_folder_being_written(tiny_dataset, tmp_path, capsys):
    pred = tmp_path / "pred"
    pred.mkdir()
    with Holder(pred) as other:  # predict writing it
        assert main(["evaluate", str(pred), "--data", str(tiny_dataset)]) == 1
    assert f"scoring {pred}: it is in use by pid {other.pid}" in capsys.readouterr().err


def test_the_record_hashes_the_split_predict_read(tiny_dataset, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    read = hashlib.sha256((data / "test.npz").read_bytes()).hexdigest()
    load_split(data, "test")
    (data / "test.npz").unlink()  # replaced after it was read, as prepare --overwrite does
    shutil.copy(data / "val.npz", data / "test.npz")
    assert loaded_split_digest(data, "test") == read


def test_complete_never_replaces_a_file_it_did_not_write(tmp_path, capsys):
    scan = tmp_path / "scan.xyz"
    np.savetxt(scan, np.random.default_rng(0).random((2000, 3)))
    out = tmp_path / "out"
    out.mkdir()
    mine = out / "scan_completed.ply"
    mine.write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nend_header\n")
    assert main(["complete", str(scan), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert f"{mine} exists and pfnet did not write it; pass --overwrite" in err
    assert mine.read_text().startswith("ply\nformat ascii")
    assert main(["complete", str(scan), "--out", str(out), "--overwrite"]) == 0
    assert main(["complete", str(scan), "--out", str(out)]) == 0  # its own files: replaced
    assert sorted(p.name for p in out.iterdir()) == ["scan_completed.ply", "scan_missing.ply"]


def test_two_inputs_with_one_stem_are_refused(tmp_path, capsys):
    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
        np.savetxt(tmp_path / folder / "scan.xyz", np.random.default_rng(0).random((100, 3)))
    argv = ["complete", str(tmp_path / "a/scan.xyz"), str(tmp_path / "b/scan.xyz")]
    assert main([*argv, "--out", str(tmp_path / "out")]) == 1
    assert "would both write scan_completed.ply" in capsys.readouterr().err


def _dead_pid() -> int:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def test_prepare_removes_only_its_own_stale_temporary_folders(tiny_dataset, tmp_path):
    splits = {s: load_split(tiny_dataset, s) for s in ("train", "val", "test")}
    dead = _dead_pid()
    stale = tmp_path / f"data.tmp-{dead}"  # a SIGKILLed prepare's
    stale.mkdir()
    (stale / TEMPORARY_MARK).touch()
    (stale / "test.npz").write_bytes(b"half")
    users = tmp_path / f"data.tmp-{dead + 1}"  # the user's, merely named so
    users.mkdir()
    (users / "notes.txt").write_text("mine")
    write_dataset(tmp_path / "data", splits, {"format_version": 1}, overwrite=False)
    assert not stale.exists()
    assert (users / "notes.txt").read_text() == "mine"
    assert not (tmp_path / "data" / TEMPORARY_MARK).exists()
    own = tmp_path / f"again.tmp-{os.getpid()}"  # this process's name, not pfnet's folder
    own.mkdir()
    (own / "notes.txt").write_text("mine")
    with pytest.raises(DataError, match="is not a temporary folder of pfnet prepare"):
        write_dataset(tmp_path / "again", splits, {"format_version": 1})
    assert (own / "notes.txt").read_text() == "mine"


def test_predict_reruns_leave_no_hidden_files(tmp_path):
    pytest.importorskip("torch")
    from pfnet.data import prepare_dataset

    data, out = tmp_path / "data", tmp_path / "pred"
    prepare_dataset(None, data, format="procedural", points=2048, seed=0, count=3,
                    categories=["chair", "table"], workers=1, progress=False)  # fmt: skip
    argv = ["predict", "--data", str(data), "--out", str(out), "--device", "cpu"]
    assert main(argv) == 0
    category = next(p for p in out.iterdir() if p.is_dir())
    (category / ".x.0123456789ab.tmp.npy").write_bytes(b"killed")  # a killed run's writes
    (out / ".predictions.0123456789ab.tmp.json").write_text("{")
    assert main(argv) == 0
    assert [p for p in out.rglob(".*")] == []
