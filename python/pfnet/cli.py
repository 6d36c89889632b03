"""The ``pfnet`` command line: one entry point, one module per subcommand.

Each subcommand lives in its own module, which exposes

* ``HELP`` — a one-line summary for ``pfnet --help``,
* ``add_arguments(parser)`` — its options,
* ``run(args) -> int`` — the work; the exit code.

Command modules import heavy dependencies (torch, trimesh, matplotlib) inside ``run`` so
that ``pfnet --help`` and ``import pfnet`` stay fast and work without torch.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from pfnet.errors import PfnetError

# name -> module implementing HELP / add_arguments / run
COMMANDS: dict[str, str] = {
    "prepare": "pfnet.data.cli",
    "train": "pfnet.training.cli",
    "predict": "pfnet.predict",
    "complete": "pfnet.complete",
    "evaluate": "pfnet.evaluate",
    "render": "pfnet.render",
    "models": "pfnet.list_models",
    "demo": "pfnet.demo",
    "reproduce": "pfnet.reproduce",
    "export": "pfnet.commands.export",
}


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
        cmd = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(cmd)
        cmd.set_defaults(_run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``pfnet`` with ``argv`` (default: ``sys.argv[1:]``); return the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except KeyboardInterrupt:
        print(f"pfnet {args.command}: interrupted", file=sys.stderr)
        return 130
    except (PfnetError, ValueError, TypeError) as err:
        print(f"pfnet {args.command}: error: {err}", file=sys.stderr)
        return 1
    except OSError as err:  # a full disk, a permission, a path that vanished: not a bug
        where = f": {err.filename}" if err.filename else ""
        print(f"pfnet {args.command}: error: {err.strerror or err}{where}", file=sys.stderr)
        return 1
    except MemoryError:
        print(f"pfnet {args.command}: error: out of memory", file=sys.stderr)
        return 1
    except ModuleNotFoundError as err:
        if (err.name or "").split(".")[0] != "torch":
            raise  # a missing module of our own is a bug: show it
        print(
            f"pfnet {args.command}: error: this command needs PyTorch, which is not "
            "installed: pip install 'pfnet[train]'",
            file=sys.stderr,
        )
        return 1


if __name__ == "__main__":
    sys.exit(main())
