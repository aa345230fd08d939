"""scripts/reproduction_tables.py, which makes docs/reproduction.md's tables from the committed
curves: its arguments, and the paired comparison on the committed runs."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

from tests.script_support import ROOT, run_script

SCRIPT = ROOT / "scripts" / "reproduction_tables.py"
DEMONSTRATIONS = ROOT / "docs" / "reproduction" / "demonstrations"


def paired_rows(output: str) -> list[list[str]]:
    """The cells of the first table (the paired differences), one list per environment."""
    first = output.split("BAM minus each other learner")[0]
    lines = [line for line in first.splitlines() if line.startswith("| ")]
    return [[cell.strip() for cell in line.strip("|").split("|")] for line in lines]


def run(*arguments: str) -> subprocess.CompletedProcess[str]:
    return run_script(SCRIPT, *arguments, timeout=300)


def test_help_describes_the_script() -> None:
    result = run("--help")
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("usage:")
    assert "--versus" in result.stdout


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        ([], "the following arguments are required: FOLDER"),
        (["no-such-folder"], "'no-such-folder' holds no curves.csv"),
        (["--versus", str(DEMONSTRATIONS)], "--versus takes exactly two experiment folders"),
    ],
)
def test_bad_arguments_exit_non_zero_with_a_message(arguments: list[str], message: str) -> None:
    result = run(*arguments)
    assert result.returncode == 2
    assert message in result.stderr
    assert "Traceback" not in result.stderr


def test_an_experiment_against_itself_differs_by_nothing() -> None:
    """Paired by agent, a run minus itself is +0.0 ± 0.0 in every cell, over all 50 agents."""
    result = run("--versus", str(DEMONSTRATIONS), str(DEMONSTRATIONS))
    assert result.returncode == 0, result.stderr
    assert "paired by agent (50 agents)" in result.stdout
    header, *rows = paired_rows(result.stdout)
    assert header[1] == "BAM, rounds 1-10"
    assert len(rows) == 8
    for row in rows:
        assert all(re.fullmatch(r"[+-]0\.0 ± 0\.0", cell) for cell in row[1:]), row


def gap_rows(output: str) -> dict[str, dict[str, str]]:
    """The cells of the learners' differences table, by environment and column."""
    table = output.split("differences between learners")[1].split("###")[0]
    lines = [line for line in table.splitlines() if line.startswith("| ")]
    header, *rows = [[cell.strip() for cell in line.strip("|").split("|")] for line in lines]
    return {row[0]: dict(zip(header, row, strict=True)) for row in rows}


def test_the_committed_run_shows_what_the_report_says() -> None:
    """docs/reproduction.md, section 4.2: over rounds 1-10, BAM is ahead of both alternatives
    by more than twice the standard error in both farming environments and against cloning
    in gravity, and not behind either anywhere by more than twice it."""
    result = run(str(DEMONSTRATIONS))
    assert result.returncode == 0, result.stderr
    gaps = gap_rows(result.stdout)
    assert len(gaps) == 8

    def gap(environment: str, other: str) -> tuple[float, float]:
        mean, error = gaps[environment][f"BAM − {other}, rounds 1-10"].split(" ± ")
        return float(mean), float(error)

    for environment in ("Two Fields", "Three Fields", "Flip", "Choices"):
        mean, error = gap(environment, "Behavioral Cloning")
        assert mean > 2 * error, environment
    for environment in ("Two Fields", "Three Fields"):
        mean, error = gap(environment, "Model-Based IRL")
        assert mean > 2 * error, environment
    for environment in gaps:
        for other in ("Model-Based IRL", "Behavioral Cloning"):
            mean, error = gap(environment, other)
            assert mean > -2 * error, (environment, other)


def test_a_run_of_bam_alone_gets_no_empty_gap_table(tmp_path: Path) -> None:
    """With one learner there is no gap to another: the comparison has the paired table only."""
    curves = (DEMONSTRATIONS / "curves.csv").read_text().splitlines()
    bam_only = tmp_path / "bam-only"
    bam_only.mkdir()
    kept = [curves[0], *(line for line in curves[1:] if line.split(",")[2] == "bam")]
    (bam_only / "curves.csv").write_text("\n".join(kept) + "\n")
    result = run("--versus", str(DEMONSTRATIONS), str(bam_only))
    assert result.returncode == 0, result.stderr
    assert "BAM minus each other learner" not in result.stdout
    header, *rows = paired_rows(result.stdout)
    assert header == ["Environment", "BAM, rounds 1-10", "BAM, round 10"]
    assert len(rows) == 8
    for row in rows:
        assert all(re.fullmatch(r"[+-]0\.0 ± 0\.0", cell) for cell in row[1:]), row
