"""The ``pfnet`` command line: one entry point, one module per subcommand.

Each subcommand lives in :mod:`pfnet.commands` as a module that exposes

* ``HELP`` — a one-line summary for ``pfnet --help``,
* ``add_arguments(parser)`` — its options,
* ``run(args) -> int`` — the work (calls into the library); the exit code.

Command modules import heavy dependencies (torch, trimesh, matplotlib) inside ``run`` so
that ``pfnet --help`` and ``import pfnet`` stay fast and work without torch.

:func:`main` is the one error boundary. The errors in :data:`USER_ERRORS` (bad input, bad
files, the machine's limits), a symbolic link loop and a missing PyTorch are printed in one
line with exit code 1, Ctrl-C exits 130; every other exception is a bug and propagates with
its traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from pfnet import errors
from pfnet.errors import PfnetError
from pfnet.io.paths import tolerant_streams

# name -> module implementing HELP / add_arguments / run
COMMANDS: dict[str, str] = {
    name: f"pfnet.commands.{name}"
    for name in (
        "prepare",
        "train",
        "predict",
        "complete",
        "evaluate",
        "render",
        "models",
        "demo",
        "reproduce",
        "export",
    )
}

USER_ERRORS: tuple[type[BaseException], ...] = (
    PfnetError,  # DataError, ConfigError: bad input files or options
    OSError,  # a full disk, a permission, a path that vanished
    MemoryError,  # an input too large for this machine
    # The geometry core's errors (bad shapes, non-finite points), once it raises its own
    # class; a plain ValueError from it is a case the Python side failed to check: a bug.
    *((errors.GeometryError,) if getattr(errors, "GeometryError", None) else ()),
)
"""What :func:`main` reports in one line: errors of the user's input or of the machine."""

SYMLINK_LOOP = "Symlink loop from "
"""How ``Path.resolve()`` before Python 3.13 words the error of a symbolic link loop."""


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser with every registered subcommand."""
    from pfnet import __version__

    parser = argparse.ArgumentParser(
        prog="pfnet",
        description="PF-Net point cloud completion: prepare data, train, predict, evaluate.",
    )
    parser.add_argument("--version", action="version", version=f"pfnet {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, module_name in COMMANDS.items():
        module = importlib.import_module(module_name)
        cmd = sub.add_parser(
            name,
            help=module.HELP,
            description=module.HELP,
            epilog=getattr(module, "EPILOG", None),
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        module.add_arguments(cmd)
        cmd.set_defaults(_run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``pfnet`` with ``argv`` (default: ``sys.argv[1:]``); return the exit code.

    Raises:
        Exception: Anything but :data:`USER_ERRORS` and a missing PyTorch: a bug, shown
            with its traceback.
    """
    # a path whose bytes are not UTF-8 is printed escaped, never a UnicodeEncodeError
    with tolerant_streams():
        return _main(argv)


def _main(argv: Sequence[str] | None) -> int:
    try:
        args = build_parser().parse_args(argv)
    except KeyboardInterrupt:  # while the command modules load
        print("pfnet: interrupted", file=sys.stderr)
        return 130
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        print(f"pfnet {args.command}: interrupted", file=sys.stderr)
        return 130
    except ModuleNotFoundError as err:
        if (err.name or "").split(".")[0] != "torch":
            raise  # a missing module of our own is a bug: show it
        print(
            f"pfnet {args.command}: error: this command needs PyTorch, which is not "
            "installed: pip install torch (the [train] extra of pfnet-completion; CPU only: add "
            "--index-url https://download.pytorch.org/whl/cpu)",
            file=sys.stderr,
        )
        return 1
    except BrokenPipeError:
        if not _stdout_gone():
            raise  # another pipe: a bug, shown
        return 128 + 13  # what a Unix tool killed by SIGPIPE returns, quietly
    except USER_ERRORS as err:
        print(f"pfnet {args.command}: error: {_one_line(err)}", file=sys.stderr)
        return 1
    except RuntimeError as err:
        if str(err).startswith(SYMLINK_LOOP):  # pathlib's resolve(); an OSError from 3.13 on
            loop = str(err)[len(SYMLINK_LOOP) :]
            print(f"pfnet {args.command}: error: a symbolic link loop: {loop}", file=sys.stderr)
            return 1
        # torch.OutOfMemoryError (CPU or CUDA) is a RuntimeError; named so that this module
        # need not import torch
        if type(err).__name__ != "OutOfMemoryError":
            raise
        print(f"pfnet {args.command}: error: out of memory ({_first(err)})", file=sys.stderr)
        return 1


def _stdout_gone() -> bool:
    """Whether the reader of stdout went away (``pfnet models --json | head``); if so, stdout
    now writes to the null device, so that flushing it at exit raises nothing more."""
    import os
    import select

    try:
        fd = sys.stdout.fileno()
        poller = select.poll()
        poller.register(fd, select.POLLOUT)
        # a pipe whose reading end is closed polls as an error
        gone = any(event & select.POLLERR for _, event in poller.poll(0))
    except (AttributeError, OSError, ValueError):  # no descriptor (a captured stream), no poll
        return False
    if gone:
        os.dup2(os.open(os.devnull, os.O_WRONLY), fd)
    return gone


def _first(err: BaseException) -> str:
    """The first line of an error's message, at most 200 characters."""
    return (str(err).splitlines() or [type(err).__name__])[0][:200]


def _one_line(err: BaseException) -> str:
    """The message of a user error: an OSError's reason and file, not its errno."""
    if isinstance(err, MemoryError):
        return "out of memory"
    if isinstance(err, OSError):
        where = f": {err.filename}" if err.filename else ""
        # an OSError raised with a message only (numpy's, on a full disk) has no strerror,
        # and once a file is set on it str() reads "[Errno None] None": keep the message
        said = next((a for a in err.args if isinstance(a, str) and a.strip()), None)
        return f"{err.strerror or said or type(err).__name__}{where}"
    return str(err)


if __name__ == "__main__":
    sys.exit(main())
