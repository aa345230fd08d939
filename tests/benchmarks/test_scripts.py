"""The README runs the benchmarks as scripts (`python benchmarks/learners.py`): run that way,
the script's folder comes first on sys.path, where benchmarks/server.py would shadow the
``server`` package. Each script must import the project and parse its arguments."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from tests.script_support import ROOT, load_script, run_script

BENCHMARKS = ROOT / "benchmarks"


def run_benchmark(script: str, *arguments: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """A benchmark script run as the README runs it, from another folder."""
    return run_script(BENCHMARKS / script, *arguments, cwd=cwd)


@pytest.mark.parametrize("script", ["learners.py", "simulate.py", "server.py", "compare.py"])
def test_a_benchmark_script_starts_as_the_readme_runs_it(script: str, tmp_path: Path) -> None:
    result = run_benchmark(script, "--help", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("usage:")


@pytest.mark.parametrize(
    ("script", "arguments", "message"),
    [
        ("learners.py", ["--environments", "nowhere"], "invalid choice: 'nowhere'"),
        ("learners.py", ["--threads", "0"], "--threads must be at least 1"),
        ("compare.py", ["--against", "no-such-revision"], "'no-such-revision' is not a commit"),
        ("compare.py", ["--against", "HEAD", "--cycles", "0"], "--cycles must be at least 1"),
        ("server.py", ["--warm-alternations", "2"], "--warm-alternations needs --optimizer"),
        (
            "server.py",
            ["--optimizer", "warm-lbfgs", "--warm-alternations", "-1"],
            "--warm-alternations must be at least 0",
        ),
    ],
)
def test_a_bad_benchmark_argument_exits_non_zero_with_a_message(
    script: str, arguments: list[str], message: str, tmp_path: Path
) -> None:
    result = run_benchmark(script, *arguments, cwd=tmp_path)
    assert result.returncode == 2
    assert message in result.stderr
    assert "Traceback" not in result.stderr


@pytest.mark.slow
def test_compare_times_both_versions_of_the_same_update(tmp_path: Path) -> None:
    """Against HEAD itself (the same code twice): one row per environment, both versions
    timed, and the temporary worktree gone afterwards."""
    result = run_benchmark(
        "compare.py",
        *("--against", "HEAD", "--environments", "wall", "--learner", "model-based"),
        *("--rounds", "1", "--repeats", "1", "--cycles", "1"),
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr
    rows = [line.split() for line in result.stdout.splitlines() if line.startswith("wall ")]
    assert len(rows) == 1
    before, after = float(rows[0][1].removesuffix("ms")), float(rows[0][2].removesuffix("ms"))
    assert before > 0 and after > 0
    # The table shows whole milliseconds and the ratio of the unrounded times to two places,
    # so the ratio lies within what the rounded times allow (a 10 ms update is +-5% wide).
    ratio = float(rows[0][5])
    assert (after - 0.5) / (before + 0.5) - 0.005 <= ratio <= (after + 0.5) / (before - 0.5) + 0.005
    worktrees = subprocess.run(
        ["git", "worktree", "list"], cwd=ROOT, capture_output=True, text=True, check=True
    )
    assert "bam-compare-" not in worktrees.stdout


def test_the_server_benchmark_s_learner_settings_are_a_valid_study_file(tmp_path: Path) -> None:
    """--fast-learners, --optimizer and --warm-alternations become [learner_settings] tables
    that the study file loader accepts, each for the learners that have the setting."""
    from server.app.config import DEFAULT_STUDY_CONFIG, load_study_config

    module = load_script(BENCHMARKS / "server.py", "server_benchmark")
    study = tmp_path / "study.toml"
    study.write_text(
        DEFAULT_STUDY_CONFIG.read_text() + module.learner_settings_toml(True, "warm-lbfgs", 2)
    )
    config = load_study_config(study)
    assert config.learner_settings["bam"] == {
        **module.FAST_LEARNERS["bam"],
        "optimizer": "warm-lbfgs",
        "warm_alternations": 2,
    }
    assert config.learner_settings["model-based"] == {
        **module.FAST_LEARNERS["model-based"],
        "optimizer": "warm-lbfgs",
    }
