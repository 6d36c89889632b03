"""``pfnet prepare`` end to end through ``pfnet.cli.main``."""

from __future__ import annotations

from pathlib import Path

import pytest

from pfnet.cli import main
from pfnet.data import load_split, read_manifest
from pfnet.data.benchmarks import BENCHMARK_FORMATS
from pfnet.data.sources.registry import FORMATS


def test_prepare_procedural(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "ds"
    argv = ["prepare", "procedural", "--out", str(out), "--count", "5", "--points", "64"]
    assert main([*argv, "--categories", "chair,lamp", "--seed", "2", "--workers", "1"]) == 0
    printed = capsys.readouterr().out
    assert f"wrote {out}: 10 shapes from procedural" in printed
    assert "chair" in printed and "lamp" in printed and "sofa" not in printed
    manifest = read_manifest(out)
    assert manifest["seed"] == 2 and manifest["categories"] == ["chair", "lamp"]
    assert load_split(out, "train").points.shape[1:] == (64, 3)
    # a second run refuses to overwrite, then replaces with --overwrite
    assert main(argv) == 1
    assert "pfnet prepare: error:" in capsys.readouterr().err
    assert main([*argv, "--overwrite", "--test-fraction", "0.4", "--val-fraction", "0"]) == 0
    assert read_manifest(out)["splits"]["test"]["total"] == 10


def test_prepare_mesh_folder_with_format(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "src" / "box"
    folder.mkdir(parents=True)
    (folder / "cube.obj").write_text(
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nv 1 0 1\nv 1 1 1\nv 0 1 1\n"
        "f 1 2 3 4\nf 5 6 7 8\nf 1 2 6 5\nf 2 3 7 6\nf 3 4 8 7\nf 4 1 5 8\n"
    )
    (folder / "bad.stl").write_bytes(b"\x00" * 10)
    code = main(
        [
            "prepare",
            str(tmp_path / "src"),
            "--out",
            str(tmp_path / "ds"),
            "--format",
            "meshes",
            "--points",
            "32",
        ]
    )
    assert code == 0
    printed = capsys.readouterr().out
    assert "skipped 1 files:" in printed and "bad.stl: the mesh has no" in printed
    code = main(
        [
            "prepare",
            str(tmp_path / "src"),
            "--out",
            str(tmp_path / "ds2"),
            "--points",
            "32",
            "--strict",
        ]
    )
    assert code == 1
    assert "bad.stl" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--points", "4"], r"points must be an integer in \[16, 65536\]"),
        (["--test-fraction", "1.5"], r"test_fraction must be in \[0, 1\)"),
        (["--categories", "boat"], "categories: boat not in the source"),
    ],
)
def test_prepare_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str], extra, message) -> None:
    assert (
        main(["prepare", "procedural", "--out", str(tmp_path / "ds"), "--count", "2", *extra]) == 1
    )
    err = capsys.readouterr().err
    assert err.startswith("pfnet prepare: error:")
    import re

    assert re.search(message, err)


def test_prepare_missing_source(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["prepare", str(tmp_path / "nope"), "--out", str(tmp_path / "ds")]) == 1
    assert "nope: no such file or folder" in capsys.readouterr().err


@pytest.mark.parametrize(
    "fmt",
    [f for f in (*FORMATS, *BENCHMARK_FORMATS) if f != "procedural"],
)
def test_every_format_but_procedural_needs_a_source_path(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], fmt: str
) -> None:
    # the benchmark formats used to fail with a TypeError traceback
    out = tmp_path / "pp" / "c"
    assert main(["prepare", "procedural", "--out", str(out), "--format", fmt]) == 1
    err = capsys.readouterr().err
    assert err == f"pfnet prepare: error: the {fmt} format needs a source path\n"
    assert not (tmp_path / "pp").exists()


def test_prepare_names_overwrite_for_a_folder_that_is_not_empty(tmp_path: Path, capsys) -> None:
    out = tmp_path / "ds"
    out.mkdir()
    (out / "x").write_text("mine")
    assert main(["prepare", "procedural", "--out", str(out), "--count", "2"]) == 1
    assert "(pass --overwrite to replace it)" in capsys.readouterr().err
    assert (out / "x").read_text() == "mine"
