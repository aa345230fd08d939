"""The participant flow (arrived to analysed) and whether rejected participants count."""

from __future__ import annotations

from pathlib import Path

from analysis.data import load_tables
from analysis.results import analyze

from .conftest import small_study, write_csv, write_export

REVIEW_COLUMNS = ("participant_id", "decision", "decision_state")


def write_reviews(folder: Path, decisions: dict[str, str]) -> None:
    write_csv(
        folder / "reviews.csv",
        REVIEW_COLUMNS,
        [
            {"participant_id": p, "decision": d, "decision_state": "done"}
            for p, d in decisions.items()
        ],
    )


def test_rejected_participants_are_left_out_by_default_and_counted_on_request(
    tmp_path: Path,
) -> None:
    folder = write_export(tmp_path / "export", small_study())
    write_reviews(folder, {"p1": "approved", "p2": "rejected", "p3": "approved", "p4": "approved"})
    notes: list[str] = []
    sessions, evaluations = load_tables(folder, notes=notes)
    assert set(sessions["participant_id"]) == {"p1", "p3", "p4"}
    assert set(evaluations["participant_id"]) == {"p1", "p3", "p4"}
    assert notes[-1] == (
        "left out 6 learning sessions of 1 participant whose submission was rejected "
        "(reviews.csv or Prolific); --include-rejected counts them"
    )
    table = analyze(sessions, evaluations).table1
    assert set(table["sessions"]) == {3}

    notes = []
    sessions, evaluations = load_tables(folder, include_rejected=True, notes=notes)
    assert set(sessions["participant_id"]) == {"p1", "p2", "p3", "p4"}
    assert notes[-1] == (
        "--include-rejected: counted 6 learning sessions of 1 participant whose submission "
        "was rejected (reviews.csv or Prolific)"
    )
    assert set(analyze(sessions, evaluations).table1["sessions"]) - {3} == {4}


def test_a_rejection_made_on_prolific_counts_as_one(tmp_path: Path) -> None:
    folder = write_export(tmp_path / "export", small_study())
    rows = [
        {"participant_id": f"p{n}", "status": "submitted", "prolific_status": status}
        for n, status in enumerate(["APPROVED", "AWAITING REVIEW", "REJECTED", ""], start=1)
    ]
    write_csv(folder / "participants.csv", ("participant_id", "status", "prolific_status"), rows)
    sessions, _ = load_tables(folder)
    assert set(sessions["participant_id"]) == {"p1", "p2", "p4"}
    sessions, _ = load_tables(folder, include_rejected=True)
    assert set(sessions["participant_id"]) == {"p1", "p2", "p3", "p4"}
