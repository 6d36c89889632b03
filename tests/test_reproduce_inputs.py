"""``pfnet reproduce`` on inputs it must refuse in one line: a README that is not UTF-8 text
or too large, an edited or forged ``results.json``, a data set without a validation split."""

from __future__ import annotations

import copy
import json
import shutil
from pathlib import Path

import pytest

from pfnet.cli import main
from pfnet.errors import DataError
from pfnet.study import README_BEGIN, README_END, update_readme
from pfnet.study.record import check_results, read_results
from pfnet.study.report import MAX_README_BYTES
from pfnet.study.runs import MAX_RUNS

RESULTS = Path(__file__).resolve().parent.parent / "results" / "study"
needs_results = pytest.mark.skipif(
    not (RESULTS / "results.json").is_file(), reason="no published results"
)


def _readme(path: Path, body: bytes) -> Path:
    path.write_bytes(body + f"\n{README_BEGIN}\n{README_END}\n".encode())
    return path


def test_a_readme_that_is_not_utf8_or_too_large_is_refused_unread(tmp_path: Path) -> None:
    latin = _readme(tmp_path / "latin.md", "# Café\n".encode("latin-1"))
    with pytest.raises(DataError, match=r"README .*latin.md is not UTF-8 text \(byte 5\)"):
        update_readme(latin, "x")
    checkpoint = tmp_path / "best.pt"
    checkpoint.write_bytes(b"PK\x03\x04\x80\xff" * 100)
    with pytest.raises(DataError, match="best.pt is not UTF-8 text"):
        update_readme(checkpoint, "x")
    sparse = _readme(tmp_path / "sparse.md", b"# x")
    with open(sparse, "r+b") as file:
        file.truncate(2 << 30)  # 2 GB apparent, a few KB on disk
    with pytest.raises(DataError, match="sparse.md is larger than 16 MB"):
        update_readme(sparse, "x")
    assert MAX_README_BYTES == 16 << 20
    assert latin.read_bytes().startswith("# Café".encode("latin-1"))  # left as it was


@needs_results
def test_report_only_refuses_a_bad_readme_before_rebuilding(tmp_path: Path, capsys) -> None:
    out = tmp_path / "results"
    shutil.copytree(RESULTS, out)
    latin = _readme(tmp_path / "latin.md", "# Café\n".encode("latin-1"))
    before = (out / "results.md").read_bytes()
    (out / "results.md").unlink()
    assert main(["reproduce", "--out", str(out), "--report-only", "--readme", str(latin)]) == 1
    err = capsys.readouterr().err
    assert f"README {latin} is not UTF-8 text" in err and "Traceback" not in err
    assert not (out / "results.md").exists()  # refused before anything was written
    assert before


def _forged(record: dict, edit) -> dict:
    forged = copy.deepcopy(record)
    edit(forged)
    return forged


@needs_results
@pytest.mark.parametrize(
    ("edit", "problem"),
    [
        (
            lambda r: r["runs"][0]["curve"].__setitem__("val_cd_l2", ["x"] * 70),
            "runs[0].curve.val_cd_l2 must hold a finite number for each of the 70 epochs",
        ),
        (
            lambda r: r["runs"][0]["curve"].__setitem__("epoch", [1, 2, 3]),
            "runs[0].curve.epoch must list the epochs 1 to 70",
        ),
        (
            lambda r: r["runs"][1]["curve"]["val_cd_l2"].__setitem__(5, float("inf")),
            "runs[1].curve.val_cd_l2 must hold a finite number",
        ),
        (
            lambda r: r["runs"][0].__setitem__("model", "zzz"),
            "runs[0]: model must be one of pfnet, pfnet-vanilla, mr-cmlp, cmlp, mlp",
        ),
        (lambda r: r["settings"][0].__setitem__("model", "zzz"), "settings are not the runs"),
        (
            lambda r: r["runs"][0].__setitem__("missing_ratio", "0.25"),
            "runs[0]: missing_ratio must be a number in (0, 1)",
        ),
        (
            lambda r: r["runs"][0].__setitem__("n_missing", -3),
            "runs[0]: n_missing must be an integer >= 1",
        ),
        (
            lambda r: r["runs"][3]["missing"]["categories"].pop("bed"),
            "runs[3].missing: other categories",
        ),
        (lambda r: r["runs"].pop(), "the runs are not those of a study"),
        (lambda r: r["runs"][2].__setitem__("name", "/etc"), "the runs are not those of a study"),
        (lambda r: r["runs"][0].pop("steps"), "runs must all have steps (a study sized in steps)"),
        (
            lambda r: r["train_dataset"].__setitem__("source", "\x1b[31mred"),
            "train_dataset.source must be printable text",
        ),
        (lambda r: r.__setitem__("runs", r["runs"] * 120), f"a study has at most {MAX_RUNS}"),
        (lambda r: r.__setitem__("seeds", list(range(40))), "seeds must be a list of 1 to 30"),
        (lambda r: r["dataset"].__setitem__("credits", [1]), "dataset.credits must be a list"),
    ],
)
def test_forged_study_records_are_refused_whole(edit, problem) -> None:
    record = json.loads((RESULTS / "results.json").read_text())
    check_results(record)  # the published record passes
    with pytest.raises(ValueError) as err:
        check_results(_forged(record, edit))
    assert problem in str(err.value)


@needs_results
def test_report_only_on_forged_records_is_one_line_and_fast(tmp_path: Path, capsys) -> None:
    """The figures came after the report's check and drew anything: tracebacks, and 20,000
    runs (55 MB, under the size cap) plotted for minutes."""
    out = tmp_path / "results"
    shutil.copytree(RESULTS, out)
    record = json.loads((out / "results.json").read_text())
    many = _forged(record, lambda r: r.__setitem__("runs", r["runs"] * 120))
    for forged, problem in (
        (many, f"1,680 runs; a study has at most {MAX_RUNS}"),
        (
            _forged(record, lambda r: r["runs"][0]["curve"]["epoch"].pop()),
            "runs[0].curve.epoch must list the epochs 1 to 70",
        ),
    ):
        (out / "results.json").write_text(json.dumps(forged))
        assert main(["reproduce", "--out", str(out), "--report-only"]) == 1
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "Traceback" not in err
        assert f"{out / 'results.json'} is not a study record this pfnet can report" in err
        assert problem in err
    with pytest.raises(DataError, match="not a regular file"):
        read_results(out)


def test_reproduce_bounds_the_seeds_and_ratios(tmp_path: Path, capsys) -> None:
    out = str(tmp_path / "r")
    seeds = [str(s) for s in range(31)]
    assert main(["reproduce", "--out", out, "--seeds", *seeds]) == 1
    assert "--seeds: at most 30 seeds" in capsys.readouterr().err
    ratios = [str(r / 100) for r in range(10, 20)]
    assert main(["reproduce", "--out", out, "--ratios", *ratios]) == 1
    assert "--ratios: at most 9 missing ratios, 0.25 included" in capsys.readouterr().err


def test_reproduce_refuses_a_data_set_without_validation_shapes(tmp_path: Path, capsys) -> None:
    pytest.importorskip("torch")
    from pfnet.data import prepare_dataset

    data = tmp_path / "data"  # what `pfnet prepare procedural --count 4` makes: val is empty
    prepare_dataset(
        None, data, format="procedural", points=256, count=4, seed=0, workers=1, progress=False
    )
    assert json.loads((data / "manifest.json").read_text())["splits"]["val"]["total"] == 0
    out = tmp_path / "study"
    argv = ["reproduce", "--out", str(out), "--data", str(data), "--device", "cpu"]
    assert main([*argv, "--models", "mlp", "--ratios", "0.25", "--epochs", "1"]) == 1
    err = capsys.readouterr().err
    assert f"data set {data} has no shapes in its val split" in err
    assert "Prepare it again with a larger validation" in err and "Traceback" not in err
    assert not out.exists()  # refused before any training


@needs_results
def test_publish_refuses_run_files_that_are_links(tmp_path: Path) -> None:
    """Audit 11: a run file planted as a link published its target's contents."""
    from pfnet.errors import DataError
    from pfnet.study import publish

    out = tmp_path / "results"
    shutil.copytree(RESULTS, out)
    secret = tmp_path / "outside.txt"
    secret.write_text("not for publication")
    run = next((out / "runs").iterdir())
    (run / "eval-missing.json").unlink()
    (run / "eval-missing.json").symlink_to(secret)
    with pytest.raises(DataError, match="goes through a link"):
        publish(out, tmp_path / "pub")
    assert not (tmp_path / "pub").exists()


def test_publish_refuses_other_pfnet_folders_and_its_own_runs(tmp_path: Path) -> None:
    """Audit 11 (N3): --publish into a data set or into the study's own runs/ folder."""
    from pfnet.errors import DataError
    from pfnet.study import publish

    out = tmp_path / "results"
    shutil.copytree(RESULTS, out)
    data = tmp_path / "data"
    data.mkdir()
    (data / "manifest.json").write_text("{}")
    with pytest.raises(DataError, match=f"cannot publish into {data}: it is a prepared data set"):
        publish(out, data)
    assert [p.name for p in data.iterdir()] == ["manifest.json"]
    before = sorted(p.relative_to(out) for p in out.rglob("*"))
    with pytest.raises(DataError, match="inside the results folder"):
        publish(out, out / "runs")
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == before
