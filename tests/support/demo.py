"""A small `bam-study demo` (two participants, one round each, two update processes) run once
per test process and shared by the tests that only read what it wrote (its printed lines, its
database, its export and analysis): a whole study takes about a minute, and the same seed
gives the same study (tests/analysis/test_demo.py checks it with a second run)."""

from __future__ import annotations

import io
from contextlib import redirect_stderr, redirect_stdout
from dataclasses import dataclass
from pathlib import Path

import pytest

from server.commands.main import main

# Two participants, one round each, two update processes: a whole study in about a minute.
SMALL_DEMO = ("--participants", "2", "--concurrency", "2", "--rounds", "1", "--workers", "2")


@dataclass(frozen=True)
class DemoRun:
    """One run of ``bam-study demo --out OUT``: its exit code and what it printed."""

    out: Path
    code: int
    stdout: str
    stderr: str


def run_small_demo(out: Path) -> DemoRun:
    """``bam-study demo --out OUT`` with ``SMALL_DEMO``'s options, in this process."""
    stdout, stderr = io.StringIO(), io.StringIO()
    with redirect_stdout(stdout), redirect_stderr(stderr):
        try:
            code = main(["demo", "--out", str(out), *SMALL_DEMO])
        except SystemExit as exit:  # argparse refused the arguments
            code = int(exit.code or 0)
    return DemoRun(out, code, stdout.getvalue(), stderr.getvalue())


@pytest.fixture(scope="session")
def small_demo(tmp_path_factory: pytest.TempPathFactory) -> DemoRun:
    """The small demo, run once per test process; a test that uses it must not change its
    folder (it writes anything of its own under its own ``tmp_path``)."""
    return run_small_demo(tmp_path_factory.mktemp("small-demo") / "demo")
