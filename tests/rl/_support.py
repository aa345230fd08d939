"""Running a snippet in a new Python program, as a user of the environments or datasets would."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPOSITORY = Path(__file__).resolve().parents[2]


def run_python(code: str, cwd: Path = REPOSITORY, **environment: str) -> str:
    """The standard output of ``python -c code`` (which must succeed) with only ``environment``
    and the repository on the path."""
    result = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        cwd=cwd,
        env={"PATH": "", "PYTHONPATH": str(REPOSITORY), **environment},
    )
    assert result.returncode == 0, result.stderr
    return result.stdout
