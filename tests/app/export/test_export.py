"""The export: CSV files with the documented columns, a data dictionary describing every column,
one evaluation per update, pseudonymised worker ids unless asked otherwise."""

from __future__ import annotations

import csv
import io
import re
import sqlite3
import zipfile
from datetime import datetime
from pathlib import Path
from types import SimpleNamespace

import pandas as pd
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from server.app.export.columns import BOOL, DICTIONARY, FILES, INT, NUMBER, TIME, Column
from server.app.export.files import export_files
from server.app.export.read import Context, Study
from server.app.export.tables import export_tables, table_frame
from server.app.storage.db import Database
from server.app.storage.models import Event, LearnerUpdate, LearningSession
from server.commands.main import main
from server.commands.simulated import SimulatedParticipant, TeachingPlan
from tests.support.server import ADMIN_TOKEN, wait_for_updates

EVALUATION_COLUMNS = [
    "session_id", "participant_id", "domain", "environment", "learner", "position",
    "update_index", "episodes", "actions", "normalized_return",
]  # fmt: skip
SESSION_COLUMNS = [
    "session_id", "participant_id", "domain", "environment", "learner", "position",
    "started_at", "finished_at", "completed",
]  # fmt: skip
PLAN = TeachingPlan(min_rounds=1, max_rounds=1, agent_try_probability=0.3, max_agent_steps=8)


@pytest.fixture
def study_run(client: TestClient, db: Database) -> list:
    runs = [
        SimulatedParticipant(
            "http://testserver", index, 7, PLAN, client=TestClient(client.app)
        ).take_part()
        for index in range(2)
    ]
    assert [run.error for run in runs] == [None, None]
    wait_for_updates(db)
    return runs


def export(database_url: str, out: Path, *flags: str) -> dict[str, pd.DataFrame]:
    assert main(["export", "--database-url", database_url, "--out", str(out), *flags]) == 0
    return {path.stem: pd.read_csv(path) for path in out.glob("*.csv")}


def test_the_export_has_the_documented_columns(
    study_run: list, db: Database, tmp_path: Path
) -> None:
    url = db.engine.url.render_as_string(hide_password=False)
    tables = export(url, tmp_path / "out")
    assert set(tables) == {*DICTIONARY, "data_dictionary"}
    for name, columns in DICTIONARY.items():
        assert list(tables[name].columns) == list(columns), name
    assert list(tables["evaluations"].columns[: len(EVALUATION_COLUMNS)]) == EVALUATION_COLUMNS
    assert list(tables["sessions"].columns[: len(SESSION_COLUMNS)]) == SESSION_COLUMNS
    dictionary = tables["data_dictionary"]
    described = set(zip(dictionary["file"], dictionary["column"].fillna(""), strict=True))
    for name, frame in tables.items():
        if name != "data_dictionary":
            for column in frame.columns:
                assert (f"{name}.csv", column) in described
    sessions = tables["sessions"]
    assert len(sessions) == 12 and sessions["completed"].all()
    assert sorted(sessions["position"].unique()) == list(range(6))
    assert len(tables["tutorial_sessions"]) == 2
    assert (tables["participants"]["status"] == "submitted").all()
    check_kinds(export_tables(db), tmp_path / "out")
    check_pseudonyms(study_run, url, tmp_path)


def check_kinds(tables: dict[str, pd.DataFrame], out: Path) -> None:
    """Each column's declared kind matches what the export holds and writes: an integer column
    is written without a decimal point, and a column that holds only integers is declared one."""
    cell_is = {
        INT: lambda cell: re.fullmatch(r"-?[0-9]+", cell) is not None,
        NUMBER: lambda cell: re.fullmatch(r"-?[0-9]+(\.[0-9]+)?(e-?[0-9]+)?", cell) is not None,
        BOOL: lambda cell: cell in ("True", "False"),
        TIME: lambda cell: datetime.fromisoformat(cell).utcoffset() is not None,
    }
    for name, columns in FILES.items():
        with (out / f"{name}.csv").open(newline="") as file:
            rows = list(csv.DictReader(file))
        for column in columns:
            held = tables[name][column.name]
            if column.kind != INT:
                assert not pd.api.types.is_integer_dtype(held.dtype), (name, column.name)
            check = cell_is.get(column.kind)
            if check is not None:
                cells = [row[column.name] for row in rows if row[column.name] != ""]
                assert all(check(cell) for cell in cells), (name, column.name, cells[:3])


def test_one_evaluation_per_update(study_run: list, client: TestClient, db: Database) -> None:
    tables = export_tables(db.engine.url.render_as_string(hide_password=False))
    evaluations = tables["evaluations"]
    with db.read() as s:
        expected = s.scalar(
            select(func.count())
            .select_from(LearnerUpdate)
            .join(LearningSession)
            .where(LearningSession.kind == "study")
        )
        episodes = {
            x.id: x.episodes
            for x in s.scalars(select(LearningSession).where(LearningSession.kind == "study"))
        }
    assert len(evaluations) == expected
    for session_id, group in evaluations.groupby("session_id"):
        assert list(group["update_index"]) == list(range(episodes[session_id] + 1))
        assert list(group["episodes"]) == list(range(episodes[session_id] + 1))
        assert group["actions"].is_monotonic_increasing
        assert group["normalized_return"].between(0, 1 + 1e-9).all()
    assert (evaluations["status"] == "done").all()
    # Episodes and events agree with the sessions.
    sessions = tables["sessions"].set_index("session_id")
    ended = tables["episodes"].dropna(subset=["ended_at"]).groupby("session_id").size()
    assert (ended.reindex(sessions.index) == sessions["episodes"]).all()
    with db.read() as s:
        assert len(tables["events"]) == s.scalar(select(func.count()).select_from(Event))
    assert sum(run.acknowledged for run in study_run) == len(tables["events"])
    check_admin_zip(client, evaluations)


def test_each_episode_and_event_names_its_session_in_the_file_of_its_kind(
    study_run: list, db: Database
) -> None:
    """A study session's rows by session_id (sessions.csv), a tutorial's by
    tutorial_session_id (tutorial_sessions.csv), the other column empty: each a foreign key
    into one file."""
    tables = export_tables(db)
    with db.read() as s:
        kind_of = {x.id: x.kind for x in s.scalars(select(LearningSession))}
        of_event = {
            event_id: session for event_id, session in s.execute(select(Event.id, Event.session_id))
        }
    files = {"study": tables["sessions"], "tutorial": tables["tutorial_sessions"]}
    assert all(len(frame) for frame in files.values())
    for name, key in (("episodes", "episode_id"), ("events", "event_id")):
        table = tables[name]
        study, tutorial = table["session_id"], table["tutorial_session_id"]
        assert not (study.notna() & tutorial.notna()).any(), name
        assert tutorial.notna().any() and study.notna().any(), name
        given = study.fillna(tutorial)
        for kind, frame in files.items():
            column = study if kind == "study" else tutorial
            assert set(column.dropna()) <= set(frame["session_id"]), (name, kind)
            assert all(kind_of[int(x)] == kind for x in column.dropna()), (name, kind)
        if name == "events":
            expected = [of_event[int(x)] for x in table[key]]
            assert [None if pd.isna(x) else int(x) for x in given] == expected
        else:
            assert given.notna().all()
            assert list(table["session_kind"]) == [kind_of[int(x)] for x in given]


def check_pseudonyms(study_run: list, url: str, tmp_path: Path) -> None:
    """Worker ids are pseudonymised (stably) unless asked otherwise."""
    hidden = export(url, tmp_path / "hidden")["participants"]
    again = export(url, tmp_path / "again")["participants"]
    shown = export(url, tmp_path / "shown", "--no-pseudonymize")["participants"]
    workers = {run.worker_id for run in study_run}
    assert set(shown["platform_participant_id"]) == workers
    assert not set(hidden["platform_participant_id"]) & workers
    assert hidden["platform_participant_id"].str.match(r"^w_[0-9a-f]{16}$").all()
    assert list(hidden["platform_participant_id"]) == list(
        again["platform_participant_id"]
    )  # stable for one database
    assert hidden["completion_code"].isna().all()
    assert set(shown["completion_code"]) == {run.completion_code for run in study_run}
    for text in (tmp_path / "hidden").glob("*.csv"):
        for worker in workers:
            assert worker not in text.read_text()


def check_admin_zip(client: TestClient, evaluations: pd.DataFrame) -> None:
    """The admin download is the same export, zipped."""
    response = client.get(
        "/api/admin/export.zip", headers={"Authorization": f"Bearer {ADMIN_TOKEN}"}
    )
    assert response.status_code == 200
    assert response.headers["content-type"] == "application/zip"
    assert "attachment" in response.headers["content-disposition"]
    archive = zipfile.ZipFile(io.BytesIO(response.content))
    assert set(archive.namelist()) == {f"{name}.csv" for name in DICTIONARY} | {
        "data_dictionary.csv"
    }
    assert pd.read_csv(archive.open("evaluations.csv")).shape == evaluations.shape


def test_exporting_a_database_without_the_schema_fails_clearly(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    empty = tmp_path / "empty.db"
    sqlite3.connect(empty).close()  # a SQLite database with no tables
    url = f"sqlite:///{empty}"
    assert main(["export", "--database-url", url, "--out", str(tmp_path / "out")]) == 1
    assert "db upgrade" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_exporting_a_missing_sqlite_file_fails_clearly_and_creates_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    missing = tmp_path / "missing.db"
    url = f"sqlite:///{missing}"
    assert main(["export", "--database-url", url, "--out", str(tmp_path / "out")]) == 1
    assert f"no database file {missing}" in capsys.readouterr().err
    assert sorted(tmp_path.iterdir()) == []  # no empty missing.db (nor -wal, -shm, out/)


def test_text_cells_that_a_spreadsheet_would_run_are_neutralised(
    client: TestClient, db: Database
) -> None:
    admin = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
    reasons = {
        "-": "-2+3",
        "=": '=HYPERLINK("http://example.org","x")',
        "+": "+1",
        "@": "@SUM(A1)",
        "tab": "\t=1",
        "plain": "left early",
    }
    for number, reason in enumerate(reasons.values(), start=1):
        worker = "-W" if number == 1 else f"W{number}"
        arrival = {
            "assignmentId": f"A{number}", "hitId": "H", "workerId": worker,
            "turkSubmitTo": "https://www.mturk.com",
        }  # fmt: skip
        assert client.post("/api/arrivals", json=arrival).status_code == 201
        excluded = client.post(
            f"/api/admin/participants/{number}/exclusion", json={"reason": reason}, headers=admin
        )
        assert excluded.status_code == 200
    response = client.get("/api/admin/export.zip?pseudonymize=false", headers=admin)
    with zipfile.ZipFile(io.BytesIO(response.content)) as archive:
        participants = list(csv.DictReader(io.StringIO(archive.read("participants.csv").decode())))
        changes = list(csv.DictReader(io.StringIO(archive.read("status_changes.csv").decode())))
        dictionary = archive.read("data_dictionary.csv").decode()
    written = [row["exclusion_reason"] for row in participants]
    assert written == ["'" + r if r != "left early" else r for r in reasons.values()]
    assert participants[0]["platform_participant_id"] == "'-W"
    notes = [row["note"] for row in changes if row["status"] == "excluded"]
    assert notes == written
    # The numbers stay numbers, and the data dictionary says what was done.
    assert [row["participant_id"] for row in participants] == ["1", "2", "3", "4", "5", "6"]
    assert "apostrophe" in dictionary
    # The database keeps the text as given.
    assert (
        client.get("/api/admin/participants/1", headers=admin).json()["exclusion_reason"] == "-2+3"
    )


LINE_BREAKS = [
    "\r",
    "\n",
    "\r\n",
    "\x0b",
    "\x0c",
    "\x1c",
    "\x1d",
    "\x1e",
    "\x85",
    "\u2028",
    "\u2029",
]


@pytest.mark.parametrize(
    "brk", LINE_BREAKS, ids=[f"U+{ord(b[0]):04X}{len(b)}" for b in LINE_BREAKS]
)
def test_every_line_of_a_text_cell_is_guarded_and_its_line_breaks_quoted(brk: str) -> None:
    """A line break inside a text answer neither splits the row (for a CSV reader or one that
    splits lines as Python does) nor lets a line after it run as a formula."""
    answers = [f"fine{brk}@SUM(1+1)", f"ok{brk}={brk}-2", "=1", "plain"]
    frame = pd.DataFrame(
        {"participant_id": [1, 2, 3, 4], "answer": answers, "points": [1.5, -2.0, 3.0, 4.0]}
    )
    text = export_files({"questionnaire_answers": frame})["questionnaire_answers.csv"].decode()
    # Read back as CSV: four rows, each answer whole, every line after a break guarded.
    rows = list(csv.DictReader(io.StringIO(text, newline="")))
    assert [row["participant_id"] for row in rows] == ["1", "2", "3", "4"]
    assert [row["answer"] for row in rows] == [
        f"fine{brk}'@SUM(1+1)",
        f"ok{brk}'={brk}'-2",
        "'=1",
        "plain",
    ]
    assert [row["points"] for row in rows] == ["1.5", "-2.0", "3.0", "4.0"]
    # Split as Python splits lines: no line starts a formula, and every break is in quotes.
    for line in text.splitlines():
        assert not line.startswith(("=", "+", "-", "@", "\t")), repr(line)
    assert text.count('"') == 4  # the two answers with a break, quoted; nothing else


def test_a_value_read_from_a_field_that_is_not_there_raises() -> None:
    """A misspelt field fails the export instead of leaving its column empty."""
    study = Study(*([()] * 12))
    context = Context.of(study, pseudonymize=False, secret=None)
    row = SimpleNamespace(participant_id=3, rows={"events": 2})
    assert table_frame((Column("participant_id", "", INT),), [row], context).iloc[0, 0] == 3
    with pytest.raises(AttributeError, match="participant_idd"):
        table_frame((Column("participant_idd", "", INT),), [row], context)
    with pytest.raises(KeyError, match="event"):
        table_frame(
            (Column("events_rows", "", INT, lambda e, ctx: e.rows["event"]),), [row], context
        )
