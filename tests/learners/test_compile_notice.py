"""A command about to compile the learners' kernels says so first: the check of numba's cache
follows its index files, and the notice speaks only when they are missing."""

from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path

import pytest

from server.learners import compile_notice

PROBE = """
from pathlib import Path
from server.learners import _kernels
from server.learners.compile_notice import kernels_cached
print(kernels_cached(), Path(_kernels.soft_forward_tasks._cache._cache_path))
"""


def _probe(cache: Path) -> tuple[str, Path]:
    environment = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    answer = subprocess.run(
        [sys.executable, "-c", PROBE], env=environment, capture_output=True, text=True, check=True
    ).stdout.split()
    return answer[0], Path(answer[1])


def test_the_kernels_count_as_cached_once_numba_s_index_is_newer_than_their_source(
    tmp_path: Path,
) -> None:
    cached, folder = _probe(tmp_path / "numba")  # an empty cache: a first run
    assert cached == "False" and folder.is_relative_to(tmp_path / "numba")
    folder.mkdir(parents=True, exist_ok=True)  # numba may have made it
    index = folder / "_kernels.soft_forward_tasks-497.py311.nbi"
    index.write_bytes(b"")
    source = Path(compile_notice._kernels.__file__).stat().st_mtime
    os.utime(index, (source - 60, source - 60))  # made before the source changed: stale
    assert _probe(tmp_path / "numba")[0] == "False"
    os.utime(index, (source + 60, source + 60))
    assert _probe(tmp_path / "numba")[0] == "True"


@pytest.mark.parametrize("cached", [True, False])
def test_the_notice_speaks_before_and_after_a_compile_only(
    cached: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(compile_notice, "kernels_cached", lambda: cached)
    said = io.StringIO()
    with compile_notice.compile_notice(said, "bam-study check"):
        said.write("(working)\n")
    lines = said.getvalue().splitlines()
    if cached:
        assert lines == ["(working)"]
    else:
        assert lines[0].startswith("bam-study check: note: this command compiles the learners'")
        assert "about a minute" in lines[0] and lines[1] == "(working)"
        assert lines[2].startswith("bam-study check: note: the kernels were compiled in ")
    # A pool's first jobs compile in their own processes: no time of ours to report.
    said = io.StringIO()
    with compile_notice.compile_notice(said, "bam-study simulate", "the first jobs"):
        pass
    assert len(said.getvalue().splitlines()) == (0 if cached else 1)
