"""Running the project's scripts (benchmarks/, scripts/) as the README and docs run them:
``python path/to/script.py`` in a subprocess, or loaded as a module to call its functions."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]


def run_script(
    script: Path, *arguments: str, cwd: Path = ROOT, timeout: float = 600
) -> subprocess.CompletedProcess[str]:
    """The script run by path: its folder, not the project, comes first on sys.path."""
    return subprocess.run(
        [sys.executable, str(script), *arguments],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def load_script(script: Path, name: str) -> ModuleType:
    """The script as a module called ``name`` (not its file name: benchmarks/server.py would
    take the name of the ``server`` package)."""
    spec = importlib.util.spec_from_file_location(name, script)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module
