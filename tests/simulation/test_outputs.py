"""A small run writes every file with exactly the documented columns and sensible values, and
the same seed gives the same numbers whatever ``--jobs`` is."""

from __future__ import annotations

import json
import math
import statistics
from pathlib import Path

from server.commands.main import main
from server.simulation.outputs import SUMMARY_COLUMNS
from server.simulation.protocols import CURVE_COLUMNS
from tests.simulation.conftest import (
    AGENTS,
    ENVIRONMENTS,
    ROUNDS,
    read_csv,
    small_args,
    without_timing,
)

LEARNERS = ("bam", "model-based", "cloning")


def test_every_file_is_written(small_run: Path) -> None:
    names = {path.name for path in small_run.iterdir()}
    expected = {
        "curves.csv",
        "summary.csv",
        "feedback.png",
        "feedback.svg",
        "report.md",
        "run.json",
        "jobs.jsonl",
        ".lock",
    }
    assert names == expected
    assert (small_run / "feedback.png").read_bytes().startswith(b"\x89PNG\r\n\x1a\n")
    assert "<svg" in (small_run / "feedback.svg").read_text(encoding="utf-8")


def test_curves_have_exactly_the_columns_and_every_round(small_run: Path) -> None:
    columns, rows = read_csv(small_run / "curves.csv")
    assert columns == list(CURVE_COLUMNS)
    assert columns == [
        "experiment",
        "environment",
        "learner",
        "agent",
        "round",
        "normalized_return",
        "total_return",
        "optimal_return",
        "update_seconds",
    ]
    seen = {(r["environment"], r["learner"], int(r["agent"]), int(r["round"])) for r in rows}
    expected = {
        (environment, learner, agent, round_)
        for environment in ENVIRONMENTS
        for learner in LEARNERS
        for agent in range(AGENTS)
        for round_ in range(ROUNDS + 1)
    }
    assert seen == expected
    assert len(rows) == len(expected)
    assert {row["experiment"] for row in rows} == {"feedback"}


def test_curve_values_are_ratios_of_returns(small_run: Path) -> None:
    _, rows = read_csv(small_run / "curves.csv")
    for row in rows:
        normalized = float(row["normalized_return"])
        total = float(row["total_return"])
        optimal = float(row["optimal_return"])
        assert -1e-9 <= normalized <= 1 + 1e-9
        assert optimal > 0
        assert math.isclose(normalized, total / optimal, rel_tol=1e-12, abs_tol=1e-12)
        seconds = float(row["update_seconds"])
        if row["round"] == "0":
            assert seconds == 0.0
        else:
            assert seconds > 0.0
    # The agents learn something: after the last round every learner beats its start.
    for environment in ENVIRONMENTS:
        for learner in LEARNERS:
            start = [
                float(r["normalized_return"])
                for r in rows
                if (r["environment"], r["learner"], r["round"]) == (environment, learner, "0")
            ]
            end = [
                float(r["normalized_return"])
                for r in rows
                if (r["environment"], r["learner"], r["round"])
                == (environment, learner, str(ROUNDS))
            ]
            assert statistics.mean(end) > statistics.mean(start) + 0.1


def test_summary_is_mean_and_standard_error_of_the_curves(small_run: Path) -> None:
    columns, summary = read_csv(small_run / "summary.csv")
    assert columns == list(SUMMARY_COLUMNS)
    _, curves = read_csv(small_run / "curves.csv")
    assert len(summary) == len(ENVIRONMENTS) * len(LEARNERS) * (ROUNDS + 1)
    for row in summary:
        values = [
            float(c["normalized_return"])
            for c in curves
            if (c["environment"], c["learner"], c["round"])
            == (row["environment"], row["learner"], row["round"])
        ]
        assert int(row["agents"]) == len(values) == AGENTS
        mean = float(row["mean_normalized_return"])
        assert math.isclose(mean, statistics.mean(values), rel_tol=1e-12, abs_tol=1e-15)
        assert -1e-9 <= mean <= 1 + 1e-9
        se = float(row["se_normalized_return"])
        expected_se = statistics.stdev(values) / math.sqrt(len(values))
        assert math.isclose(se, expected_se, rel_tol=1e-9, abs_tol=1e-15)
        assert row["experiment"] == "feedback"


def test_report_has_settings_table_figure_and_time(small_run: Path) -> None:
    report = (small_run / "report.md").read_text(encoding="utf-8")
    assert "## Settings" in report
    assert "**alternations=2**" in report and "**steps=20**" in report
    assert "| Environment | Learner | Round 0 | Round 1 | Round 2 |" in report
    for title in ("| Wall | BAM |", "| Doorway | Behavioral Cloning |"):
        assert title in report
    assert "![" in report and "(feedback.png)" in report
    assert "learner updates" in report and "Wall time" in report
    run = json.loads((small_run / "run.json").read_text(encoding="utf-8"))
    assert run["arguments"]["learner_settings"]["cloning"] == {"steps": 20}
    assert "steps" not in run["arguments"]["learner_settings"]["bam"]


def test_same_seed_same_numbers_with_one_and_two_jobs(small_run: Path, tmp_path: Path) -> None:
    out = tmp_path / "two-jobs"
    assert main(small_args(out, "feedback", "--jobs", "2")) == 0
    for name in ("curves.csv", "summary.csv"):
        assert without_timing(out / name) == without_timing(small_run / name)
        # Apart from measured time, the files are byte for byte the same.
        assert read_csv(out / name)[0] == read_csv(small_run / name)[0]


def test_another_seed_gives_other_numbers(small_run: Path, tmp_path: Path) -> None:
    out = tmp_path / "seed"
    args = small_args(out, "feedback", "--jobs", "1", "--agents", "1", "--environments", "wall")
    args[args.index("--seed") + 1] = "8"
    assert main(args) == 0
    other = {
        (r["learner"], r["round"]): r["normalized_return"]
        for r in without_timing(out / "curves.csv")
    }
    ours = {
        (r["learner"], r["round"]): r["normalized_return"]
        for r in without_timing(small_run / "curves.csv")
        if r["environment"] == "wall" and r["agent"] == "0"
    }
    assert other.keys() == ours.keys()
    assert any(other[key] != ours[key] for key in other if key[1] != "0")
