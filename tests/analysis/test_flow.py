"""The participant flow (arrived to analysed) and whether rejected participants count."""

from __future__ import annotations

import csv
import itertools
import re
from collections import Counter
from pathlib import Path

import pandas as pd
import pytest

from analysis.data import load_tables
from analysis.flow import AFTER_CONSENT, BEFORE_CONSENT, IN_STUDY, STAGES, participant_flow
from analysis.results import analyze
from server.app.export.columns import STATUS_COLUMNS
from server.commands.main import main

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


# Participants beyond the four of the small study (all submitted), one or more in every other
# status: (status, how many of their six agents they taught; None: no learning sessions).
OTHERS = {
    "r1": ("returned", 5),
    "r2": ("returned", 0),  # returned during the tutorial: six agents, none taught
    "t1": ("abandoned", 2),
    "i1": ("teaching", 3),
    "i2": ("questionnaire", 6),
    "i3": ("consented", 0),
    "d1": ("declined", None),
    "d2": ("declined", None),
    "w1": ("waiting", None),
    "a1": ("arrived", None),
    "r3": ("returned", None),  # before consenting
    "t2": ("abandoned", None),
    "c1": ("submitted", 6),  # rejected
    "c2": ("completed", 6),  # excluded by the experimenter
    "c3": ("submitted", 6),  # flagged poor_demonstrations
    "c4": ("submitted", 6),  # flagged long_idle and poor_demonstrations
    "c5": ("completed", 6),  # flagged long_idle, rejected as well
}
ERASURES = [  # (erased_by, learning sessions erased)
    ("participant", 6),
    ("participant", 0),  # withdrew at the consent page
    ("experimenter", 6),
]
FLAGGED = {"c3": "poor_demonstrations", "c4": "long_idle poor_demonstrations", "c5": "long_idle"}
REJECTED = {"c1", "c5"}


def agents(participant: str, taught: int, first: int):
    """Six sessions of ``participant`` (ids from ``first``), the first ``taught`` taught."""
    rows = []
    for slot in range(6):
        environment = "two-rooms" if slot < 3 else "doorway"
        learner = ("bam", "model-based", "cloning")[slot % 3]
        curve = [(0, 0, 0.0), (3, 40, 0.6), (6, 80, 0.9)] if slot < taught else [(0, 0, 0.0)]
        rows.append((f"x{first + slot}", participant, environment, learner, slot, curve))
    return rows


def every_status_export(folder: Path) -> tuple[Path, dict[str, str]]:
    sessions = small_study()
    statuses = {f"p{n}": "submitted" for n in range(1, 5)}
    for number, (participant, (status, taught)) in enumerate(OTHERS.items()):
        statuses[participant] = status
        if taught is not None:
            sessions += agents(participant, taught, 100 + 10 * number)
    write_export(folder, sessions, participants=statuses, excluded={"c2"})
    write_reviews(
        folder,
        {
            p: "rejected" if p in REJECTED else "approved"
            for p, s in statuses.items()
            if s in ("completed", "submitted")
        },
    )
    write_csv(
        folder / "quality.csv",
        ("participant_id", "flags"),
        [
            {"participant_id": p, "flags": FLAGGED.get(p, "")}
            for p, s in statuses.items()
            if s in ("completed", "submitted")
        ],
    )
    write_csv(
        folder / "erasures.csv",
        ("erasure_id", "erased_by", "learning_sessions_rows"),
        [
            {"erasure_id": n, "erased_by": by, "learning_sessions_rows": rows}
            for n, (by, rows) in enumerate(ERASURES)
        ],
    )
    return folder, statuses


def note_matching(notes: list[str], pattern: str) -> re.Match[str]:
    found = [m for m in (re.search(pattern, note) for note in notes) if m]
    assert len(found) == 1, (pattern, notes)
    return found[0]


def by_reason(text: str) -> dict[str, int]:
    """``"returned the task: 12, timed out: 6"`` -> ``{"returned the task": 12, ...}``."""
    return {k: int(v) for k, v in (part.rsplit(": ", 1) for part in text.split(", "))}


OPTIONS = {
    "default": {},
    "exclusions": {
        "exclude_excluded": True,
        "exclude_flagged": ("poor_demonstrations", "long_idle"),
    },
    "inclusions": {"include_rejected": True, "include_unfinished": True},
}


@pytest.mark.parametrize("options", OPTIONS.values(), ids=list(OPTIONS))
def test_the_flow_reconciles_with_the_statuses_and_with_table_1s_notes(
    tmp_path: Path, options: dict
) -> None:
    folder, statuses = every_status_export(tmp_path / "export")
    notes: list[str] = []
    tables: dict = {}
    sessions, evaluations = load_tables(folder, notes=notes, tables=tables, **options)
    flow = participant_flow(tables, sessions, **options)
    assert flow is not None
    analysis = analyze(sessions, evaluations, notes=notes, flow=flow)
    boxes = {box.box: box for box in flow.boxes}

    # Each stage is the one above it less those who left it, plus those added back.
    for above, below in itertools.pairwise(STAGES):
        for count in ("participants", "learning_sessions"):
            change = sum(
                getattr(b, count) * (1 if b.kind == "added" else -1) for b in flow.leaving(above)
            )
            assert getattr(flow.stage(below), count) == getattr(flow.stage(above), count) + change
    # So everyone who arrived ends in exactly one box.
    left = [b for b in flow.boxes if b.kind == "left"]
    added = sum(b.participants for b in flow.boxes if b.kind == "added")
    assert len(statuses) + len(ERASURES) == boxes["arrived"].participants
    assert boxes["arrived"].participants == (
        sum(b.participants for b in left) + boxes["analysed"].participants - added
    )
    all_sessions = sum(6 for _, taught in OTHERS.values() if taught is not None) + 24
    erased = sum(rows for _, rows in ERASURES)
    assert boxes["arrived"].learning_sessions == all_sessions + erased

    # The boxes are the export's statuses.
    status = Counter(statuses.values())
    assert boxes["declined"].participants == status["declined"]
    assert boxes["waiting"].participants == status["waiting"]
    assert boxes["at_consent"].participants == status["arrived"]
    assert (
        boxes["returned"].participants + boxes["returned_before_consent"].participants
        == status["returned"]
    )
    assert (
        boxes["timed_out"].participants + boxes["timed_out_before_consent"].participants
        == status["abandoned"]
    )
    assert boxes["returned_before_consent"].participants == sum(
        1 for s, taught in OTHERS.values() if s == "returned" and taught is None
    )
    assert boxes["in_study"].participants == sum(status[s] for s in IN_STUDY)
    assert flow.stage("completed").participants == status["completed"] + status["submitted"]
    assert boxes["withdrew"].participants + boxes["withdrew_before_consent"].participants == len(
        ERASURES
    )
    assert boxes["withdrew"].learning_sessions == erased

    # Analysed is what Table 1 counts.
    assert flow.stage("analysed").participants == analysis.summary["participant_id"].nunique()
    assert flow.stage("analysed").learning_sessions == int(analysis.table1["sessions"].sum())
    assert flow.stage("analysed").learning_sessions == len(analysis.summary)

    # And the notes under Table 1 say the same.
    unfinished = ("returned", "timed_out", "in_study")
    if options.get("include_unfinished"):
        match = note_matching(
            notes, r"counted (\d+) taught learning sessions? of (\d+) participants? who did not"
        )
        assert (int(match[1]), int(match[2])) == (
            boxes["unfinished_taught"].learning_sessions,
            boxes["unfinished_taught"].participants,
        )
    else:
        match = note_matching(
            notes,
            r"left out (\d+) learning sessions? of (\d+) participants? who did not complete the "
            r"study \(([^)]*)\)",
        )
        assert int(match[1]) == sum(boxes[b].learning_sessions for b in unfinished)
        assert int(match[2]) == sum(
            boxes[b].participants for b in unfinished if boxes[b].learning_sessions
        )
        assert by_reason(match[3]) == {
            "returned the task": boxes["returned"].learning_sessions,
            "timed out": boxes["timed_out"].learning_sessions,
            "still in the study": boxes["in_study"].learning_sessions,
        }
    if options.get("include_rejected"):
        match = note_matching(
            notes, r"counted (\d+) learning sessions? of (\d+) participants? whose"
        )
        assert "rejected" not in boxes
        counted = boxes["rejected_counted"]
        assert (int(match[1]), int(match[2])) == (counted.learning_sessions, counted.participants)
        assert counted.participants == len(REJECTED)
    else:
        match = note_matching(
            notes, r"left out (\d+) learning sessions? of (\d+) participants? whose"
        )
        rejected = boxes["rejected"]
        assert (int(match[1]), int(match[2])) == (rejected.learning_sessions, rejected.participants)
    if options.get("exclude_excluded"):
        match = note_matching(
            notes, r"excluded (\d+) learning sessions? of (\d+) participants? marked"
        )
        excluded = boxes["excluded"]
        assert (int(match[1]), int(match[2])) == (excluded.learning_sessions, excluded.participants)
        assert excluded.participants == 1
    flags = options.get("exclude_flagged", ())
    if flags:
        match = note_matching(
            notes, r"excluded (\d+) learning sessions? of (\d+) participants? flagged"
        )
        dropped = [boxes[f"flagged_{flag}"] for flag in flags]
        assert int(match[1]) == sum(b.learning_sessions for b in dropped)
        assert int(match[2]) == sum(b.participants for b in dropped)
        # Each participant once, under the first reason: c5 (long_idle) was rejected already.
        assert [b.participants for b in dropped] == [2, 0]
    else:
        flagged_ids = {p for p, words in FLAGGED.items() if "poor_demonstrations" in words}
        assert boxes["flagged_poor_demonstrations_counted"].participants == len(flagged_ids)


def run_analyze(capsys: pytest.CaptureFixture[str], *args: str | Path) -> str:
    code = main(["analyze", *(str(a) for a in args)])
    out = capsys.readouterr().out
    assert code == 0, out
    return out


def flow_rows(out: Path) -> dict[str, dict[str, str]]:
    with (out / "participant_flow.csv").open(newline="", encoding="utf-8") as file:
        return {row["box"]: row for row in csv.DictReader(file)}


def test_analyze_writes_the_flow_and_include_rejected_changes_what_counts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder, _ = every_status_export(tmp_path / "export")
    run_analyze(capsys, "--data", folder, "--out", tmp_path / "default")
    run_analyze(capsys, "--data", folder, "--out", tmp_path / "with", "--include-rejected")
    default, including = flow_rows(tmp_path / "default"), flow_rows(tmp_path / "with")
    for out, rows in ((tmp_path / "default", default), (tmp_path / "with", including)):
        summary = pd.read_csv(out / "sessions_summary.csv")
        assert int(rows["analysed"]["participants"]) == summary["participant_id"].nunique()
        assert int(rows["analysed"]["learning_sessions"]) == len(summary)
        for suffix in ("png", "svg"):
            assert (out / f"participant_flow.{suffix}").stat().st_size > 0
        readme = (out / "README.md").read_text(encoding="utf-8")
        assert "## Participant flow" in readme
        assert "`--include-rejected` counts them" in readme
    rejected = int(default["rejected"]["participants"])
    assert rejected == len(REJECTED)
    assert "rejected" not in including
    assert int(including["rejected_counted"]["participants"]) == rejected
    assert int(including["analysed"]["participants"]) == (
        int(default["analysed"]["participants"]) + rejected
    )
    assert int(including["analysed"]["learning_sessions"]) == (
        int(default["analysed"]["learning_sessions"])
        + int(default["rejected"]["learning_sessions"])
    )
    with_rejected = set(pd.read_csv(tmp_path / "with" / "sessions_summary.csv")["participant_id"])
    without = set(pd.read_csv(tmp_path / "default" / "sessions_summary.csv")["participant_id"])
    assert with_rejected - without == REJECTED


def test_without_participant_statuses_there_is_no_flow(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = write_export(tmp_path / "export", small_study())
    (folder / "participants.csv").unlink()
    run_analyze(capsys, "--data", folder, "--out", tmp_path / "out")
    assert not (tmp_path / "out" / "participant_flow.csv").exists()
    readme = (tmp_path / "out" / "README.md").read_text(encoding="utf-8")
    assert "Not drawn: no `participants.csv` with a `status` column" in readme


def test_every_status_of_the_server_has_its_place_in_the_flow() -> None:
    from server.app.storage.vocabulary import ParticipantStatus

    statuses = set(ParticipantStatus)
    assert set(BEFORE_CONSENT) | set(AFTER_CONSENT) == statuses
    # The export's participants.csv says the same statuses.
    assert statuses == set(STATUS_COLUMNS) | {"waiting"}


def test_an_unknown_or_impossible_status_still_ends_in_one_box(tmp_path: Path) -> None:
    sessions = small_study()
    statuses = {"p1": "submitted", "p2": "paused", "p3": "declined", "p4": "submitted", "p5": "x"}
    folder = write_export(tmp_path / "export", sessions, participants=statuses)
    tables: dict = {}
    counted, _ = load_tables(folder, tables=tables)
    flow = participant_flow(tables, counted)
    assert flow is not None
    boxes = {box.box: box for box in flow.boxes}
    # p2 and p3 have learning sessions, so they consented: a status that cannot follow consent
    # is named as it is; p5 (no sessions) left before consenting.
    assert boxes["status_paused"].participants == 1
    assert boxes["status_declined"].participants == 1
    assert boxes["declined"].participants == 0
    assert boxes["status_x_before_consent"].participants == 1
    left = sum(b.participants for b in flow.boxes if b.kind == "left")
    assert flow.stage("arrived").participants == len(statuses) == left + 2
    assert flow.stage("analysed").participants == 2
