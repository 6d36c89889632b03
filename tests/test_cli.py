"""The command line's error boundary: user errors in one line, bugs with their traceback."""

from __future__ import annotations

import errno

import pytest

import pfnet.commands.models
from pfnet import errors
from pfnet.cli import COMMANDS, USER_ERRORS, main
from pfnet.errors import ConfigError, DataError, PfnetError


def _raising(exc: BaseException):
    def run(_args):
        raise exc

    return run


@pytest.mark.parametrize(
    "exc",
    [
        ConfigError("width must be positive, got -1"),
        DataError("scan.ply: line 3 has 2 columns"),
        PfnetError("something the user can fix"),
    ],
)
def test_a_pfnet_error_is_one_line_and_exit_code_1(monkeypatch, capsys, exc):
    monkeypatch.setattr(pfnet.commands.models, "run", _raising(exc))
    assert main(["models"]) == 1
    err = capsys.readouterr().err
    assert err == f"pfnet models: error: {exc}\n"


def test_the_machine_s_limits_are_one_line(monkeypatch, capsys):
    full = OSError(errno.ENOSPC, "No space left on device", "/tmp/out/x.npy")
    monkeypatch.setattr(pfnet.commands.models, "run", _raising(full))
    assert main(["models"]) == 1
    assert capsys.readouterr().err == (
        "pfnet models: error: No space left on device: /tmp/out/x.npy\n"
    )
    monkeypatch.setattr(pfnet.commands.models, "run", _raising(MemoryError()))
    assert main(["models"]) == 1
    assert capsys.readouterr().err == "pfnet models: error: out of memory\n"
    monkeypatch.setattr(pfnet.commands.models, "run", _raising(KeyboardInterrupt()))
    assert main(["models"]) == 130
    assert capsys.readouterr().err == "pfnet models: interrupted\n"


def test_ctrl_c_while_the_commands_load_is_one_line(monkeypatch, capsys):
    import pfnet.cli

    def interrupted():
        raise KeyboardInterrupt

    monkeypatch.setattr(pfnet.cli, "build_parser", interrupted)
    assert main(["prepare", "procedural", "--out", "x"]) == 130
    assert capsys.readouterr().err == "pfnet: interrupted\n"


@pytest.mark.parametrize(
    "exc", [TypeError("bug"), ValueError("bug"), KeyError("bug"), AttributeError("bug")]
)
def test_a_bug_propagates_with_its_traceback(monkeypatch, capsys, exc):
    # A plain ValueError or TypeError is not the user's: it must not become one quiet line.
    from pfnet.inference import shipped

    def broken():
        raise exc

    monkeypatch.setattr(shipped, "shipped_models", broken)
    with pytest.raises(type(exc), match="bug"):
        main(["models"])
    assert "error:" not in capsys.readouterr().err


def test_user_errors_are_pfnet_s_own_and_the_machine_s():
    assert USER_ERRORS[:3] == (PfnetError, OSError, MemoryError)
    assert ValueError not in USER_ERRORS and TypeError not in USER_ERRORS
    geometry_error = getattr(errors, "GeometryError", None)
    assert (geometry_error in USER_ERRORS) == (geometry_error is not None)
    # Python callers may still catch ValueError for bad input.
    assert issubclass(ConfigError, ValueError) and issubclass(DataError, ValueError)


def test_commands_import_no_other_command():
    import ast
    import importlib.util
    from pathlib import Path

    for name, module_name in COMMANDS.items():
        assert module_name == f"pfnet.commands.{name}"
        path = Path(importlib.util.find_spec(module_name).origin)
        tree = ast.parse(path.read_text(encoding="utf-8"))
        imported = {
            node.module
            for node in ast.walk(tree)
            if isinstance(node, ast.ImportFrom) and node.module
        } | {
            alias.name
            for node in ast.walk(tree)
            if isinstance(node, ast.Import)
            for alias in node.names
        }
        assert not {m for m in imported if m.startswith("pfnet.commands")}, name
        assert "pfnet.cli" not in imported, name


def test_every_command_is_summarised_as_a_sentence_in_pfnet_help():
    import importlib

    helps = {name: importlib.import_module(module).HELP for name, module in COMMANDS.items()}
    assert {n: h for n, h in helps.items() if not (h[0].isupper() and h.endswith("."))} == {}


def test_no_module_of_the_package_is_over_500_lines():
    """docs/architecture.md's promise to a newcomer: every room is small enough to read."""
    from pathlib import Path

    import pfnet

    package = Path(pfnet.__file__).parent
    sizes = {p.relative_to(package): len(p.read_text().splitlines()) for p in package.rglob("*.py")}
    assert len(sizes) > 50
    assert {str(path): n for path, n in sizes.items() if n > 500} == {}


def test_running_out_of_memory_in_pytorch_is_one_line(monkeypatch, capsys) -> None:
    """The seventh audit: torch's OutOfMemoryError (a RuntimeError) printed a traceback."""
    import pfnet.commands.models as command

    class OutOfMemoryError(RuntimeError):  # what torch raises, by name
        pass

    def run(args):
        raise OutOfMemoryError("CUDA out of memory. Tried to allocate 2.00 GiB\nmore text")

    monkeypatch.setattr(command, "run", run)
    assert main(["models"]) == 1
    err = capsys.readouterr().err
    assert (
        err
        == "pfnet models: error: out of memory (CUDA out of memory. Tried to allocate 2.00 GiB)\n"
    )

    def bug(args):
        raise RuntimeError("a bug")

    monkeypatch.setattr(command, "run", bug)
    with pytest.raises(RuntimeError, match="a bug"):
        main(["models"])
