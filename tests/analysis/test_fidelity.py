"""``bam-study fidelity``: a run's curves beside a reference's, cell by cell."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from analysis.fidelity import compare
from server.commands.main import main

REPOSITORY = Path(__file__).resolve().parents[2]
PUBLISHED = REPOSITORY / "docs" / "reproduction"


def curves(seed: int, shift: dict[tuple[str, str], float] | None = None) -> pd.DataFrame:
    """50 agents, two environments, two learners, 5 rounds: returns drawn around a learning
    curve (spread 0.1 per agent), with ``shift`` added to whole (environment, learner) curves."""
    rng = np.random.default_rng(seed)
    rows = []
    for environment in ("wall", "flip"):
        for learner in ("bam", "model-based"):
            for agent in range(50):
                for round_ in range(6):
                    mean = 1 - 0.8 * 0.6**round_
                    value = mean + (rng.normal(0, 0.1) if round_ else 0.0)
                    value += (shift or {}).get((environment, learner), 0.0) if round_ else 0.0
                    rows.append((environment, learner, agent, round_, value))
    return pd.DataFrame(
        rows, columns=["environment", "learner", "agent", "round", "normalized_return"]
    )


def test_a_run_against_itself_is_kept_with_every_cell_at_zero() -> None:
    comparison = compare(curves(0), curves(0))
    assert len(comparison.cells) == 2 * 2 * 5  # round 0 (untaught) is left out
    assert all(cell.units == 0.0 for cell in comparison.cells)
    assert comparison.kept


def test_independent_runs_of_the_same_agents_are_kept() -> None:
    comparison = compare(curves(0), curves(1))
    assert comparison.beyond_3 == 0
    assert comparison.kept


def test_one_learner_moved_by_a_tenth_is_changed() -> None:
    # 10 percentage points on one curve: about 7 standard errors of a difference.
    comparison = compare(curves(0), curves(1, shift={("flip", "bam"): -0.1}))
    moved = [c for c in comparison.cells if (c.environment, c.learner) == ("flip", "bam")]
    assert all(c.units < -3 for c in moved)
    assert comparison.beyond_3 == 5
    assert not comparison.kept
    assert comparison.largest.learner == "bam" and comparison.largest.environment == "flip"


def test_many_cells_a_little_beyond_two_are_changed_though_none_passes_three() -> None:
    reference = curves(0)
    run = reference.copy()
    # Every cell of one learner moved by 2.5 of its standard errors: 10 of 20 cells beyond 2.
    cells = reference.assign(percent=100 * reference["normalized_return"]).groupby(
        ["environment", "learner", "round"]
    )["percent"]
    se = (cells.std(ddof=1) / np.sqrt(cells.count())).rename("se").reset_index()
    run = run.merge(se, on=["environment", "learner", "round"])
    moved = (run["learner"] == "bam") & (run["round"] >= 1)
    run.loc[moved, "normalized_return"] += 2.5 * np.sqrt(2) * run.loc[moved, "se"] / 100
    comparison = compare(reference, run.drop(columns="se"))
    assert comparison.beyond_3 == 0
    assert comparison.beyond_2 == 10
    assert not comparison.kept


def test_the_published_runs_that_share_their_agents_compare_as_identical(capsys) -> None:
    # BAM and model-based IRL see the same demonstrations in the demonstrations and global-cost
    # experiments, and their published curves are identical to the last bit.
    status = main(["fidelity", str(PUBLISHED / "demonstrations"), str(PUBLISHED / "global-cost")])
    out = capsys.readouterr().out
    assert status == 0
    assert "160 cells" in out  # 8 environments x 2 shared learners x 10 rounds
    assert "beyond 2 standard errors: 0 " in out
    assert "Verdict: **kept**" in out


def test_a_different_experiment_is_reported_changed_with_exit_1(tmp_path: Path, capsys) -> None:
    out_file = tmp_path / "fidelity.md"
    status = main(
        [
            "fidelity",
            str(PUBLISHED / "demonstrations"),
            str(PUBLISHED / "feedback" / "curves.csv"),
            "--out",
            str(out_file),
        ]
    )
    printed = capsys.readouterr().out
    assert status == 1
    assert "Verdict: **changed**" in printed
    assert out_file.read_text(encoding="utf-8") == printed
    # Every cell has its row: 8 environments x 3 learners x 10 rounds.
    assert printed.count("\n| ") == 1 + 240


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (None, "no curves.csv"),
        ("environment,learner,agent,round\nwall,bam,0,1\n", "missing column(s) normalized_return"),
        (
            "environment,learner,agent,round,normalized_return\nwall,bam,0,1,abc\n",
            "not a number",
        ),
    ],
)
def test_bad_input_is_one_line_and_exit_2(
    tmp_path: Path, capsys, content: str | None, message: str
) -> None:
    folder = tmp_path / "run"
    folder.mkdir()
    if content is not None:
        (folder / "curves.csv").write_text(content, encoding="utf-8")
    status = main(["fidelity", str(PUBLISHED / "demonstrations"), str(folder)])
    err = capsys.readouterr().err
    assert status == 2
    assert message in err
    assert len(err.strip().splitlines()) == 1


def test_runs_that_share_no_cell_are_refused(tmp_path: Path, capsys) -> None:
    other = curves(0)
    other["environment"] = "doorway"
    other.to_csv(tmp_path / "curves.csv", index=False)
    reference = curves(0)
    reference.to_csv(tmp_path / "reference.csv", index=False)
    status = main(["fidelity", str(tmp_path / "reference.csv"), str(tmp_path / "curves.csv")])
    assert status == 2
    assert "share no (environment, learner, round) cell" in capsys.readouterr().err
