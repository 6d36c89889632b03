"""A reader that stops reading (``pfnet models --json | head``) ends a command quietly."""

from __future__ import annotations

import subprocess
import sys


def test_a_closed_stdout_pipe_exits_141_without_a_traceback():
    command = [sys.executable, "-c", "import sys; from pfnet.cli import main; sys.exit(main())"]
    process = subprocess.Popen(
        [*command, "models", "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    process.stdout.close()  # the reader is gone before the command writes
    _, err = process.communicate(timeout=120)
    assert process.returncode == 141
    assert err.decode() == ""
