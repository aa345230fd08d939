"""Erasing a participant: every row of theirs goes, in every table, in one transaction, with one
audit row (``erasures``) and nothing personal in it; every row of the other participants stays
exactly as it was; the platform replicas keep their records (as MTurk and Prolific do); the export and the Minari datasets leave them out and list the erasure; the
balanced assignment no longer counts them."""

from __future__ import annotations

from collections.abc import Collection
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from server.app.errors import ApiError
from server.app.export.minari import StudyFile, study_datasets
from server.app.export.tables import export_tables
from server.app.rights.erasure import erase_participant
from server.app.rights.pseudonyms import database_secret, pseudonym
from server.app.storage.db import Database
from server.app.storage.models import (
    DEPLOYMENT_TABLES,
    Base,
    Erasure,
    LearningSession,
    Participant,
)
from server.app.study_file import StudyConfig
from tests.support.server import (
    ADMIN_TOKEN,
    demonstrate_each_task,
    new_participant,
    study_config,
    wait_for_updates,
)
from tests.support.server import Participant as ApiParticipant

ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
QUESTION = {"id": "remarks", "kind": "text", "text": "Anything to add?", "required": False}


@pytest.fixture
def study() -> StudyConfig:
    """One agent and no tutorial, then a one-question questionnaire."""
    return study_config(
        learners=["cloning"],
        domains=[{"name": "navigation", "environments": ["wall"]}],
        tutorial={"enabled": False},
        questionnaire={"questions": [QUESTION]},
    )


def replica_worker(client: TestClient, db: Database, worker: str, remark: str) -> int:
    """A worker who accepts the replica's HIT, teaches, answers the questionnaire and submits;
    then opens the study again in a second browser (a token of its own). Their id."""
    from server.app.storage.replica_models import ReplicaAssignment

    accepted = client.post(
        "/mturk/accept", data={"workerId": worker}, headers=ADMIN, follow_redirects=False
    )
    assert accepted.status_code == 303, accepted.text
    with db.read() as s:
        row = s.scalars(
            select(ReplicaAssignment).where(ReplicaAssignment.worker_id == worker)
        ).one()
        link = {
            "assignmentId": row.assignment_id,
            "hitId": row.hit_id,
            "workerId": worker,
            "turkSubmitTo": "http://testserver",
        }
    client.cookies.clear()
    arrived = client.post("/api/arrivals", json=link)
    assert arrived.status_code == 201, arrived.text
    participant = ApiParticipant(client, arrived.json()["token"])
    participant.act("/api/participant/consent", agree=True)
    session_id = participant.act("/api/participant/start")["participant"]["current_session_id"]
    demonstrate_each_task(participant, session_id)
    participant.act(f"/api/sessions/{session_id}/finish")
    done = participant.act("/api/participant/questionnaire", answers={"remarks": remark})
    assert done["participant"]["status"] == "completed"
    participant.act("/api/participant/submission")
    posted = client.post(
        "/mturk/externalSubmit",
        data=done["participant"]["completion"]["submit_fields"],
        headers=ADMIN,
    )
    assert posted.status_code == 200, posted.text
    client.cookies.clear()
    assert client.post("/api/arrivals", json=link).status_code in (200, 201)
    return int(participant.get("/api/participant")["participant_id"])


def snapshot(db: Database) -> dict[str, list[dict[str, Any]]]:
    """Every row of every table but the deployment's own (a heartbeat writes them meanwhile),
    in primary-key order."""
    with db.connect() as c:
        return {
            table.name: [
                dict(row)
                for row in c.execute(select(table).order_by(*table.primary_key.columns)).mappings()
            ]
            for table in Base.metadata.sorted_tables
            if table.name not in DEPLOYMENT_TABLES
        }


def text_in_database(db: Database, leave_out: Collection[str] = ()) -> str:
    """Every text cell of every table but those named in ``leave_out``, joined (JSON columns as
    their text)."""
    cells: list[str] = []
    for table, rows in snapshot(db).items():
        if table in leave_out:
            continue
        for row in rows:
            cells += [str(value) for value in row.values() if isinstance(value, str | dict)]
    return "\n".join(cells)


def test_an_erasure_removes_every_row_of_the_participant_and_no_other(
    client: TestClient, db: Database, tmp_path: Path
) -> None:
    first = replica_worker(client, db, "WORKERONE", "first remark")
    second = replica_worker(client, db, "WORKERTWO", "second remark")
    third = replica_worker(client, db, "WORKERTHREE", "third remark")
    for who in (first, second):
        paid = client.post(
            f"/api/admin/participants/{who}/bonuses",
            json={"amount": "0.50", "reason": "Thank you", "unique_token": f"bonus-token-{who}"},
            headers=ADMIN,
        )
        assert paid.status_code == 200, paid.text
    approved = client.post(
        f"/api/admin/participants/{second}/approval", json={"message": "ok"}, headers=ADMIN
    )
    assert approved.status_code == 200, approved.text
    wait_for_updates(db)
    with db.read() as s:
        sessions = set(
            s.scalars(select(LearningSession.id).where(LearningSession.participant_id == second))
        )
        assignment = s.scalar(
            select(Participant.platform_submission_id).where(Participant.id == second)
        )
    assert assignment is not None
    assert "WORKERTWO" in text_in_database(db) and assignment in text_in_database(db)
    before = snapshot(db)

    def theirs(table: str, row: dict[str, Any]) -> bool:
        if table == "participants":
            return bool(row["id"] == second)
        if "participant_id" in row:
            return bool(row["participant_id"] == second)
        if "session_id" in row:
            return row["session_id"] in sessions
        return False

    replica_tables = {name for name in before if name.startswith("mturk_replica_")}
    named = {
        name
        for name in replica_tables
        if any(row.get("worker_id") == "WORKERTWO" for row in before[name])
    }
    assert named == {
        "mturk_replica_assignments",
        "mturk_replica_submissions",
        "mturk_replica_bonuses",
    }

    removed = {
        table: sum(theirs(table, row) for row in rows)
        for table, rows in before.items()
        if any(theirs(table, row) for row in rows)
    }
    # The participant has rows in every table keyed to them.
    assert set(removed) >= {
        "participants",
        "learning_sessions",
        "episodes",
        "events",
        "learner_updates",
        "status_changes",
        "questionnaire_answers",
        "participant_tokens",
        "reviews",
        "bonuses",
    }

    erased = erase_participant(db, second, "experimenter")

    after = snapshot(db)
    secret = database_secret(db)
    (audit,) = after.pop("erasures")
    assert before.pop("erasures") == []
    for table, rows in before.items():
        assert after[table] == [row for row in rows if not theirs(table, row)], table
    # MTurk keeps its assignment (submitted, bonus paid): so does the replica, unchanged.
    for table in replica_tables:
        assert after[table] == before[table], table
    assert {table: count for table, count in erased.rows.items() if count} == removed
    assert not set(erased.rows) & replica_tables
    assert audit["rows"] == erased.rows
    assert (audit["participant_id"], audit["erased_by"], audit["platform"]) == (
        second,
        "experimenter",
        "mturk",
    )
    assert audit["platform_participant_pseudonym"] == pseudonym(secret, "WORKERTWO", "w")
    assert audit["platform_submission_pseudonym"] == pseudonym(secret, assignment, "a")
    left = text_in_database(db, leave_out=replica_tables)
    assert "WORKERTWO" not in left and assignment not in left and "second remark" not in left

    # The export leaves them out and lists the erasure, under the export's own pseudonyms.
    tables = export_tables(db)
    for name, frame in tables.items():
        if "participant_id" in frame.columns and name != "erasures":
            assert second not in set(frame["participant_id"]), name
    assert {first, third} <= set(tables["participants"]["participant_id"])
    assert {first, third} <= set(tables["events"]["participant_id"])
    row = tables["erasures"].iloc[0].to_dict()
    assert row["participant_id"] == second and row["erased_by"] == "experimenter"
    assert row["platform_participant_id"] == pseudonym(secret, "WORKERTWO", "w")
    assert row["events_rows"] == removed["events"] > 0
    # So do the Minari datasets.
    study_file = tmp_path / "study.toml"
    study_file.write_text("title = 'x'\n")
    datasets = study_datasets(db, StudyFile.read(study_file))
    shown = {
        int(number)
        for dataset in datasets
        for episode in dataset.episodes
        for number in episode.infos["participant"]
    }
    assert shown == {first, third}

    # Erased already: nobody to erase.
    with pytest.raises(ApiError) as gone:
        erase_participant(db, second, "experimenter")
    assert gone.value.status == 404
    with db.read() as s:
        assert len(s.scalars(select(Erasure)).all()) == 1


def test_the_balanced_assignment_no_longer_counts_an_erased_participant(
    client: TestClient, db: Database
) -> None:
    """Two domains: the first two participants fill one each; once the first is erased, the
    third gets the first's domain (the least filled, alone)."""
    client.app.state.server.study = study_config(
        learners=["cloning"],
        domains=[
            {"name": "navigation", "environments": ["wall"]},
            {"name": "farming", "environments": ["two-fields"]},
        ],
        tutorial={"enabled": False},
    )
    domains = []
    ids = []
    for worker in ("W1", "W2", "W3"):
        client.cookies.clear()
        arrived = client.post(
            "/api/arrivals",
            json={
                "assignmentId": f"A{worker}",
                "hitId": "H1",
                "workerId": worker,
                "turkSubmitTo": "https://workersandbox.mturk.com",
            },
        )
        assert arrived.status_code == 201, arrived.text
        participant = ApiParticipant(client, arrived.json()["token"])
        participant.act("/api/participant/consent", agree=True)
        state = participant.get("/api/participant")
        domains.append(state["domain"])
        ids.append(int(state["participant_id"]))
        if worker == "W2":
            assert len(set(domains)) == 2
            erase_participant(db, ids[0], "participant")
    with db.read() as s:
        third = s.get(Participant, ids[2])
        assert third is not None
        assert third.domain == domains[0]


def test_a_table_added_with_a_key_to_a_participant_is_erased_without_a_word_elsewhere() -> None:
    """Erasure and scrubbing find a participant's tables from the foreign keys: a new table
    keyed to participants, and one keyed to that one, are found, children first."""
    from sqlalchemy import Column, ForeignKey, Integer, MetaData, Table

    from server.app.rights.identifiers import study_rows

    metadata = MetaData()
    for table in Base.metadata.sorted_tables:
        table.to_metadata(metadata)
    Table(
        "notes",
        metadata,
        Column("id", Integer, primary_key=True),
        Column("participant_id", ForeignKey("participants.id")),
    )
    Table(
        "note_replies",
        metadata,
        Column("id", Integer, primary_key=True),
        Column("note_id", ForeignKey("notes.id")),
    )
    Table("unrelated", metadata, Column("id", Integer, primary_key=True))
    rows = study_rows(7, metadata)
    names = [table.name for table, _ in rows]
    today = [table.name for table, _ in study_rows(7)]
    assert set(names) == set(today) | {"notes", "note_replies"}
    assert names.index("note_replies") < names.index("notes")
    assert names.index("episodes") < names.index("learning_sessions")
    assert "unrelated" not in names and "participants" not in names
    conditions = {
        table.name: str(where.compile(compile_kwargs={"literal_binds": True}))
        for table, where in rows
    }
    assert conditions["notes"] == "notes.participant_id = 7"
    assert "note_replies.note_id IN (SELECT notes.id" in conditions["note_replies"]
    assert "notes.participant_id = 7" in conditions["note_replies"]
    # The study's own tables today, and none of the platform replicas' (their participant_id
    # is a platform's id): what erasure deletes besides the replica rows of the turn.
    assert set(today) == {
        "attention_checks",
        "bonuses",
        "episodes",
        "events",
        "learner_updates",
        "learning_sessions",
        "messages",
        "participant_tokens",
        "questionnaire_answers",
        "reviews",
        "status_changes",
    }


def test_an_erased_participants_number_is_never_given_to_another(client: TestClient) -> None:
    """SQLite gives a new row the largest id plus one: erasing the newest participant must not
    hand their number to the next arrival (erasures.csv would name two people by it)."""
    first = new_participant(client, "W1", "A1")
    second = new_participant(client, "W2", "A2")
    assert [
        first.get("/api/participant")["participant_id"],
        second.get("/api/participant")["participant_id"],
    ] == [1, 2]
    erased = client.post("/api/admin/participants/2/erasure", headers=ADMIN)
    assert erased.status_code == 200, erased.text
    third = new_participant(client, "W3", "A3")
    assert third.get("/api/participant")["participant_id"] == 3
