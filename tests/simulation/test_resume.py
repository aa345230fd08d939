"""An interrupted run started again with the same arguments continues where it stopped and
ends with the same numbers as an uninterrupted run."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from server.commands.main import main
from server.simulation import protocols
from server.simulation.config import build_config
from server.simulation.protocols import Job, JobResult
from server.simulation.runner import (
    JOURNAL_FILE,
    LocalBackend,
    SimulationError,
    plan_jobs,
    run_jobs,
)
from tests.simulation.conftest import (
    AGENTS,
    ENVIRONMENTS,
    FAST_SETTINGS,
    ROUNDS,
    small_args,
    without_timing,
)


def small_config():
    config, notes = build_config(
        "feedback", list(ENVIRONMENTS), None, AGENTS, ROUNDS, 7, list(FAST_SETTINGS)
    )
    assert notes == []
    return config


def journal_lines(out: Path) -> list[str]:
    return (out / JOURNAL_FILE).read_text(encoding="utf-8").splitlines()


def test_partial_run_then_resume_matches_uninterrupted(small_run: Path, tmp_path: Path) -> None:
    out = tmp_path / "resumed"
    config = small_config()
    total = len(plan_jobs(config))
    # An interruption after five jobs: the journal holds them, no results are written yet.
    partial = run_jobs(config, out, LocalBackend(1), max_jobs=5)
    assert not partial.complete and len(partial.results) == 5
    first = journal_lines(out)
    assert len(first) == 5
    assert not (out / "curves.csv").exists()

    assert main(small_args(out, "feedback", "--jobs", "2")) == 0
    lines = journal_lines(out)
    assert len(lines) == total  # nothing run twice
    assert lines[:5] == first  # the finished jobs were kept, not redone
    run = json.loads((out / "run.json").read_text(encoding="utf-8"))
    assert [(s["jobs_resumed"], s["jobs_run"]) for s in run["sessions"]] == [(0, 5), (5, total - 5)]
    for name in ("curves.csv", "summary.csv"):
        assert without_timing(out / name) == without_timing(small_run / name)

    # Started again once more, everything is done: nothing runs, the outputs are rewritten.
    assert main(small_args(out, "feedback", "--jobs", "1")) == 0
    assert journal_lines(out) == lines
    assert without_timing(out / "curves.csv") == without_timing(small_run / "curves.csv")


def test_a_line_cut_short_is_dropped_and_redone(small_run: Path, tmp_path: Path) -> None:
    out = tmp_path / "damaged"
    config = small_config()
    run_jobs(config, out, LocalBackend(1), max_jobs=3)
    good = journal_lines(out)
    # The process was killed while writing the fourth line.
    with (out / JOURNAL_FILE).open("a", encoding="utf-8") as handle:
        handle.write('{"job": "wall/bam/1", "seconds": 0.1, "rows": [{"experi')
    assert main(small_args(out, "feedback", "--jobs", "1")) == 0
    lines = journal_lines(out)
    assert lines[:3] == good
    assert len(lines) == len(plan_jobs(config))
    assert all(json.loads(line)["job"] for line in lines)
    assert without_timing(out / "curves.csv") == without_timing(small_run / "curves.csv")


def test_a_failing_job_stops_the_run_and_keeps_the_finished_ones(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    real = protocols._run_agent

    def failing(job: Job) -> JobResult:
        if job.key == "doorway/bam/0":
            raise FloatingPointError("the planner diverged")
        return real(job)

    monkeypatch.setattr(protocols, "_run_agent", failing)
    out = tmp_path / "failing"
    with pytest.raises(SimulationError, match="job doorway/bam/0 failed: FloatingPointError"):
        run_jobs(small_config(), out, LocalBackend(1))
    keys = [json.loads(line)["job"] for line in journal_lines(out)]
    assert keys == ["wall/bam/0", "wall/model-based/0", "wall/cloning/0"]


def test_killed_process_resumes(small_run: Path, tmp_path: Path) -> None:
    """Kill a real run (SIGKILL, no chance to clean up) once its journal has a line."""
    out = tmp_path / "killed"
    command = [
        sys.executable,
        "-m",
        "server.commands.main",
        *small_args(out, "feedback", "--jobs", "1"),
    ]
    process = subprocess.Popen(
        command,
        cwd=Path(__file__).resolve().parents[2],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    journal = out / JOURNAL_FILE
    total = len(plan_jobs(small_config()))
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and process.poll() is None:
            if journal.exists() and journal.read_text(encoding="utf-8").count("\n") >= 1:
                break
            time.sleep(0.01)
        assert process.poll() is None, "the run ended before it could be interrupted"
        os.kill(process.pid, signal.SIGKILL)
    finally:
        process.wait()
    done = len(journal_lines(out))
    assert 1 <= done < total
    assert not (out / "curves.csv").exists()
    assert main(small_args(out, "feedback", "--jobs", "1")) == 0
    assert len(journal_lines(out)) == total
    for name in ("curves.csv", "summary.csv"):
        assert without_timing(out / name) == without_timing(small_run / name)
