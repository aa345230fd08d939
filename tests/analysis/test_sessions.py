"""Loading an export and the per-session measures: reached, episodes and actions required."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest

from analysis.data import EVALUATION_COLUMNS, load_tables
from analysis.options import InputError
from analysis.stats import session_measures

from .conftest import write_csv, write_export


def measures(tmp_path: Path, sessions, thresholds=(0.5, 0.8)) -> pd.DataFrame:
    folder = write_export(tmp_path / "export", sessions)
    loaded_sessions, evaluations = load_tables(folder)
    return session_measures(loaded_sessions, evaluations, thresholds).set_index("session_id")


def test_first_evaluation_that_reaches_the_threshold_gives_the_counts(tmp_path: Path) -> None:
    curve = [(1, 10, 0.1), (2, 25, 0.4), (3, 31, 0.55), (4, 50, 0.85), (5, 60, 0.7)]
    row = measures(tmp_path, [("a", "p1", "two-rooms", "bam", 0, curve)]).loc["a"]
    assert bool(row["reached_50"]) and bool(row["reached_80"])
    assert (row["episodes_50"], row["actions_50"]) == (3, 31)
    # Reached at update 3; dropping below afterwards does not undo it.
    assert (row["episodes_80"], row["actions_80"]) == (4, 50)
    assert row["evaluations"] == 5
    assert row["best_normalized_return"] == pytest.approx(0.85)
    assert row["final_normalized_return"] == pytest.approx(0.7)


def test_a_return_equal_to_the_threshold_reaches_it(tmp_path: Path) -> None:
    curve = [(1, 12, 0.5), (2, 20, 0.79999), (3, 33, 0.8)]
    row = measures(tmp_path, [("a", "p1", "doorway", "cloning", 3, curve)]).loc["a"]
    assert (row["episodes_50"], row["actions_50"]) == (1, 12)
    assert (row["episodes_80"], row["actions_80"]) == (3, 33)


def test_a_jump_reaches_both_thresholds_at_once_and_an_optimal_return_is_allowed(
    tmp_path: Path,
) -> None:
    curve = [(2, 9, 0.1), (3, 14, 1.0000004)]  # exact scoring may round just above 1
    row = measures(tmp_path, [("a", "p1", "two-rooms", "bam", 0, curve)]).loc["a"]
    assert (row["episodes_50"], row["episodes_80"]) == (3, 3)
    assert (row["actions_50"], row["actions_80"]) == (14, 14)


def test_sessions_that_never_reach_or_have_no_evaluations(tmp_path: Path) -> None:
    summary = measures(
        tmp_path,
        [
            ("low", "p1", "two-rooms", "bam", 0, [(1, 5, 0.1), (2, 9, 0.49)]),
            ("none", "p1", "two-rooms", "cloning", 1, []),
        ],
    )
    for session in ("low", "none"):
        row = summary.loc[session]
        assert not row["reached_50"] and not row["reached_80"]
        assert pd.isna(row["episodes_50"]) and pd.isna(row["actions_80"])
    assert summary.loc["none", "evaluations"] == 0
    assert pd.isna(summary.loc["none", "best_normalized_return"])


def test_evaluations_are_taken_in_update_order_whatever_the_file_order(tmp_path: Path) -> None:
    folder = write_export(tmp_path / "export", [("a", "p1", "two-rooms", "bam", 0, [])])
    shared = {
        "session_id": "a",
        "participant_id": "p1",
        "domain": "navigation",
        "environment": "two-rooms",
        "learner": "bam",
        "position": 0,
    }
    rows = [  # update 2 reaches 0.8 at 3 episodes; update 0 is listed last
        {**shared, "update_index": 2, "episodes": 3, "actions": 40, "normalized_return": 0.9},
        {**shared, "update_index": 1, "episodes": 2, "actions": 20, "normalized_return": 0.6},
        {**shared, "update_index": 0, "episodes": 1, "actions": 10, "normalized_return": 0.3},
    ]
    write_csv(folder / "evaluations.csv", EVALUATION_COLUMNS, rows)
    sessions, evaluations = load_tables(folder)
    row = session_measures(sessions, evaluations, (0.5, 0.8)).iloc[0]
    assert (row["episodes_50"], row["episodes_80"]) == (2, 3)
    assert row["final_normalized_return"] == pytest.approx(0.9)


def test_thresholds_name_the_columns(tmp_path: Path) -> None:
    summary = measures(
        tmp_path, [("a", "p1", "two-rooms", "bam", 0, [(1, 5, 0.7)])], thresholds=(0.65,)
    )
    assert list(summary.columns[-3:]) == ["reached_65", "episodes_65", "actions_65"]
    assert bool(summary.loc["a", "reached_65"])


def test_loaded_tables_are_typed(tmp_path: Path) -> None:
    folder = write_export(tmp_path / "export", [("a", "p1", "two-rooms", "bam", 2, [(1, 5, 0.25)])])
    sessions, evaluations = load_tables(folder)
    assert sessions["position"].tolist() == [2]
    assert sessions["completed"].tolist() == [True]
    assert evaluations["episodes"].dtype.kind == "i"
    assert evaluations["normalized_return"].tolist() == [0.25]


def test_exclude_excluded_drops_the_sessions_of_excluded_participants(tmp_path: Path) -> None:
    sessions = [
        ("a", "p1", "two-rooms", "bam", 0, [(1, 5, 0.6)]),
        ("b", "p2", "two-rooms", "bam", 0, [(1, 5, 0.6)]),
        ("c", "p2", "two-rooms", "cloning", 1, [(1, 5, 0.6)]),
    ]
    folder = write_export(
        tmp_path / "export", sessions, participants={"p1": "completed", "p2": "excluded"}
    )
    notes: list[str] = []
    kept, evaluations = load_tables(folder, exclude_excluded=True, notes=notes)
    assert kept["session_id"].tolist() == ["a"]
    assert evaluations["session_id"].tolist() == ["a"]
    assert notes == [
        "excluded 2 learning sessions of 1 participant marked excluded in participants.csv"
    ]
    notes = []
    kept, _ = load_tables(folder, notes=notes)
    assert len(kept) == 3
    assert notes == [
        "2 learning sessions of participants marked excluded in participants.csv are included "
        "(--exclude-excluded drops them)"
    ]


def test_failed_learner_updates_are_left_out_with_a_note(tmp_path: Path) -> None:
    """The server exports failed updates (status ``failed``, no return): they have no
    evaluation; a missing return on a row that did not fail is still an error."""
    curve = [(0, 0, 0.0), (1, 10, 0.3), (2, 20, 0.9), (3, 30, 0.95)]
    folder = write_export(tmp_path / "export", [("a", "p1", "two-rooms", "bam", 0, curve)])
    path = folder / "evaluations.csv"
    frame = pd.read_csv(path, dtype=str, keep_default_na=False)
    frame["status"] = ["done", "done", "failed", "done"]
    frame.loc[2, "normalized_return"] = ""
    frame.to_csv(path, index=False)
    notes: list[str] = []
    sessions, evaluations = load_tables(folder, notes=notes)
    assert evaluations["update_index"].tolist() == [0, 1, 3]
    assert notes == [
        "1 failed learner update in evaluations.csv left out (no evaluation; the server's log "
        "says why)"
    ]
    row = session_measures(sessions, evaluations, (0.8,)).set_index("session_id").loc["a"]
    assert (row["episodes_80"], row["actions_80"]) == (3, 30)  # not the failed update's

    frame.loc[2, "status"] = "done"
    frame.to_csv(path, index=False)
    with pytest.raises(InputError, match=r"row 3 \(line 4\), column 'normalized_return'"):
        load_tables(folder)
