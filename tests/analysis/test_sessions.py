"""Loading an export and the per-session measures: reached, episodes and actions required."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest

from analysis.columns import EVALUATION_COLUMNS
from analysis.data import load_tables
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
    folder = write_export(tmp_path / "export", sessions, excluded={"p2"})
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


def _episode(
    session: str, update: int, kind: str, start: int, end: int, reason: str, actions: int
) -> dict[str, object]:
    return {
        "session_id": session,
        "kind": kind,
        "start_state": start,
        "end_state": end,
        "end_reason": reason,
        "actions": actions,
        "update_index": update,
    }


def test_empty_episodes_in_older_data_are_not_counted(tmp_path: Path) -> None:
    """Older servers recorded a try from the goal as an agent episode of one action that ended
    at once where it began, with its own update. Episodes and actions required leave them out;
    look-alikes that taught something still count."""
    curve = [
        (0, 0, 0.1),  # update 0: the untrained learner
        (1, 10, 0.3),  # a demonstration of 10 moves
        (2, 11, 0.3),  # empty: T on the goal
        (3, 12, 0.3),  # empty again
        (4, 20, 0.6),  # a demonstration of 8 moves reaches 50%
        (5, 21, 0.6),  # an agent's one step onto the goal from elsewhere: counts
        (6, 22, 0.6),  # one step that stayed put, stopped by the participant: counts
        (7, 23, 0.9),  # a one-move demonstration (older data: start_state after the move)
    ]
    episodes = [
        _episode("a", 1, "demonstration", 40, 7, "goal", 10),
        _episode("a", 2, "agent", 7, 7, "goal", 1),
        _episode("a", 3, "agent", 7, 7, "goal", 1),
        _episode("a", 4, "demonstration", 33, 7, "goal", 8),
        _episode("a", 5, "agent", 8, 7, "goal", 1),
        _episode("a", 6, "agent", 12, 12, "end", 1),
        _episode("a", 7, "demonstration", 7, 7, "goal", 1),
        _episode("tutorial", 1, "agent", 3, 3, "goal", 1),  # not a study session
        {**_episode("a", 8, "agent", 9, 9, "", 1), "end_reason": ""},  # still open
    ]
    folder = write_export(
        tmp_path / "export", [("a", "p1", "two-rooms", "bam", 0, curve)], episodes=episodes
    )
    notes: list[str] = []
    sessions, evaluations = load_tables(folder, notes=notes)
    assert evaluations["episodes"].tolist() == [0, 1, 1, 1, 2, 3, 4, 5]
    assert evaluations["actions"].tolist() == [0, 10, 10, 10, 18, 19, 20, 21]
    assert notes == [
        "2 empty episodes in 1 learning session not counted (an agent's try from the goal "
        "that ended there at once: one action, start_state = end_state, end_reason goal; the "
        "server no longer records these)"
    ]
    row = session_measures(sessions, evaluations, (0.5, 0.8)).set_index("session_id").loc["a"]
    assert (row["episodes_50"], row["actions_50"]) == (2, 18)
    assert (row["episodes_80"], row["actions_80"]) == (5, 21)

    # Without episodes.csv the counts are as exported, and a note says so.
    (folder / "episodes.csv").unlink()
    notes = []
    _, evaluations = load_tables(folder, notes=notes)
    assert evaluations["episodes"].tolist() == [0, 1, 2, 3, 4, 5, 6, 7]
    assert notes and "no episodes.csv given" in notes[0]


def test_an_empty_episode_without_its_update_is_a_clear_error(tmp_path: Path) -> None:
    episodes = [{**_episode("a", 1, "agent", 7, 7, "goal", 1), "update_index": "x"}]
    folder = write_export(
        tmp_path / "export",
        [("a", "p1", "two-rooms", "bam", 0, [(0, 0, 0.1), (1, 1, 0.2)])],
        episodes=episodes,
    )
    with pytest.raises(InputError, match=r"episodes.csv, row 1 \(line 2\), column 'update_index'"):
        load_tables(folder)


# Participants who completed the study, and others who did not: returned during the tutorial
# (nothing taught), timed out after teaching one agent, and one still teaching.
TAUGHT = [(0, 0, 0.1), (1, 10, 0.6)]
MIXED_STUDY = [
    ("a1", "p1", "two-rooms", "bam", 0, TAUGHT),
    ("a2", "p1", "two-rooms", "cloning", 1, TAUGHT),
    ("b1", "p2", "two-rooms", "bam", 0, TAUGHT),
    ("b2", "p2", "two-rooms", "cloning", 1, TAUGHT),
    ("r1", "p3", "two-rooms", "bam", 0, []),
    ("r2", "p3", "two-rooms", "cloning", 1, []),
    ("t1", "p4", "two-rooms", "cloning", 0, TAUGHT),
    ("t2", "p4", "two-rooms", "bam", 1, []),
    ("s1", "p5", "two-rooms", "bam", 0, TAUGHT),
    ("s2", "p5", "two-rooms", "cloning", 1, []),
]
MIXED_STATUSES = {
    "p1": "completed",
    "p2": "submitted",
    "p3": "returned",
    "p4": "abandoned",
    "p5": "teaching",
}


def test_only_the_sessions_of_participants_who_completed_the_study_are_counted(
    tmp_path: Path,
) -> None:
    """As the paper's Table 1 (58 of the 129 who began): a worker who returned the task during
    the tutorial leaves sessions nobody taught, which must not count as sessions that reached
    no threshold."""
    folder = write_export(tmp_path / "export", MIXED_STUDY, participants=MIXED_STATUSES)
    notes: list[str] = []
    sessions, evaluations = load_tables(folder, notes=notes)
    assert sessions["session_id"].tolist() == ["a1", "a2", "b1", "b2"]
    assert sorted(set(evaluations["session_id"])) == ["a1", "a2", "b1", "b2"]
    assert notes == [
        "left out 6 learning sessions of 3 participants who did not complete the study "
        "(returned the task: 2, still in the study: 2, timed out: 2); 4 never taught (no "
        "episode or action); --include-unfinished adds the 2 taught"
    ]

    notes = []
    sessions, evaluations = load_tables(folder, include_unfinished=True, notes=notes)
    assert sessions["session_id"].tolist() == ["a1", "a2", "b1", "b2", "t1", "s1"]
    assert sorted(set(evaluations["session_id"])) == ["a1", "a2", "b1", "b2", "s1", "t1"]
    assert notes == [
        "--include-unfinished: counted 2 taught learning sessions of 2 participants who did not "
        "complete the study (still in the study: 1, timed out: 1)",
        "left out 4 learning sessions never taught (no episode or action) of participants who did not "
        "complete the study (returned the task: 2, still in the study: 1, timed out: 1)",
    ]


def test_every_participant_status_of_the_server_is_completed_or_has_a_reason() -> None:
    """A status the server gives a participant is either completion or a reason, in the note,
    for not finishing; a new status needs its entry in UNFINISHED_REASONS."""
    from analysis.selection import COMPLETED_STATUSES, UNFINISHED_REASONS
    from server.app.storage.vocabulary import ParticipantStatus as STATUSES

    assert set(COMPLETED_STATUSES) <= set(STATUSES)
    assert set(STATUSES) - set(COMPLETED_STATUSES) == set(UNFINISHED_REASONS)


def test_an_unknown_or_missing_status_is_named_in_the_note(tmp_path: Path) -> None:
    study = [
        ("a", "p1", "two-rooms", "bam", 0, TAUGHT),
        ("b", "p2", "two-rooms", "bam", 0, TAUGHT),
        ("c", "p3", "two-rooms", "bam", 0, []),
    ]
    folder = write_export(tmp_path / "export", study, participants={"p1": "Submitted", "p2": "x"})
    notes: list[str] = []
    sessions, _ = load_tables(folder, notes=notes)
    assert sessions["session_id"].tolist() == ["a"]
    assert notes == [
        "left out 2 learning sessions of 2 participants who did not complete the study "
        "(not in participants.csv: 1, status 'x': 1); 1 never taught (no episode or action); "
        "--include-unfinished adds the 1 taught"
    ]


def test_without_participant_statuses_every_session_is_counted_with_a_note(
    tmp_path: Path,
) -> None:
    folder = write_export(tmp_path / "export", MIXED_STUDY, participants=MIXED_STATUSES)
    (folder / "participants.csv").unlink()
    notes: list[str] = []
    sessions, _ = load_tables(folder, notes=notes)
    assert len(sessions) == len(MIXED_STUDY)
    assert notes == [
        "participant statuses not checked (no participants.csv given): every learning session "
        "is counted, whether or not its participant completed the study"
    ]


def test_no_participant_who_completed_the_study_is_a_clear_error(tmp_path: Path) -> None:
    study = [row for row in MIXED_STUDY if row[1] in ("p3", "p4")]
    folder = write_export(tmp_path / "export", study, participants=MIXED_STATUSES)
    with pytest.raises(InputError, match="no learning sessions of participants who completed"):
        load_tables(folder)
    sessions, _ = load_tables(folder, include_unfinished=True)
    assert sessions["session_id"].tolist() == ["t1"]


def test_an_agent_evaluated_but_never_opened_is_not_taught(tmp_path: Path) -> None:
    """Every agent is evaluated before any data (update 0, no episode, no action): one the
    participant never opened has that evaluation alone, and --include-unfinished must not
    count it as taught (it added it as a session that reached no threshold)."""
    study = [
        ("a1", "p1", "two-rooms", "bam", 0, TAUGHT),
        ("a2", "p1", "two-rooms", "cloning", 1, TAUGHT),
        ("u1", "p2", "two-rooms", "bam", 0, TAUGHT),
        ("u2", "p2", "two-rooms", "cloning", 1, [(0, 0, 0.1)]),  # evaluated, never opened
    ]
    folder = write_export(
        tmp_path / "export", study, participants={"p1": "submitted", "p2": "returned"}
    )
    notes: list[str] = []
    sessions, _ = load_tables(folder, include_unfinished=True, notes=notes)
    assert sessions["session_id"].tolist() == ["a1", "a2", "u1"]
    assert any(
        "left out 1 learning session never taught (no episode or action)" in n for n in notes
    )
