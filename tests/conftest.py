"""Shared fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest

from pfnet.data import prepare_dataset


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small procedural dataset made by ``prepare_dataset``: 512 points per shape, four
    categories (chair, lamp, sofa, table), 24 train / 8 val / 12 test shapes."""
    out = tmp_path_factory.mktemp("data") / "tiny"
    prepare_dataset(
        None,
        out,
        format="procedural",
        points=512,
        seed=0,
        count=11,
        categories=["chair", "lamp", "sofa", "table"],
        test_fraction=0.25,
        val_fraction=0.2,
        workers=1,
        progress=False,
    )
    return out


@pytest.fixture
def sigint_as_in_a_terminal():
    """SIGINT handled as in a terminal for one test, whatever the test run inherited.

    A test suite started in the background by a non-interactive shell inherits SIGINT
    ignored, and ``pfnet train`` leaves an ignored SIGINT ignored (as CPython does); the
    tests of Ctrl-C set it as a terminal has it (their subprocesses inherit that too).
    """
    import signal

    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, before)
