"""The README runs the benchmarks as scripts (`python benchmarks/learners.py`): run that way,
the script's folder comes first on sys.path, where benchmarks/server.py would shadow the
``server`` package. Each script must import the project and parse its arguments."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


@pytest.mark.parametrize("script", ["learners.py", "simulate.py", "server.py"])
def test_a_benchmark_script_starts_as_the_readme_runs_it(script: str, tmp_path: Path) -> None:
    result = subprocess.run(
        [sys.executable, str(BENCHMARKS / script), "--help"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("usage:")


def test_a_bad_benchmark_argument_exits_non_zero_with_a_message(tmp_path: Path) -> None:
    result = subprocess.run(
        [sys.executable, str(BENCHMARKS / "learners.py"), "--environments", "nowhere"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2
    assert "invalid choice: 'nowhere'" in result.stderr
    assert "Traceback" not in result.stderr
