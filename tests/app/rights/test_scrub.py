"""Platform ids that expire: after ``bam-study db scrub`` (or the study's
``scrub_identifiers_after_days``) no text cell of any table holds a worker id, an assignment id
or a completion code; the export and the Minari datasets are the same as before, and a scrubbed
participant can still be found and erased by their raw worker id."""

from __future__ import annotations

from datetime import timedelta
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from server.app.export.minari import StudyFile, study_datasets
from server.app.export.tables import export_tables
from server.app.rights.scrub import scrub
from server.app.storage.db import Database
from server.app.storage.models import Erasure, Participant, utcnow
from server.app.study_file import StudyConfig
from server.commands.main import main
from tests.app.rights.test_erasure import replica_worker, snapshot, text_in_database
from tests.app.rights.test_erasure import study as study
from tests.support.server import ADMIN_TOKEN, wait_for_updates

ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}


def raw_identifiers(db: Database) -> set[str]:
    with db.read() as s:
        rows = s.execute(
            select(
                Participant.platform_participant_id,
                Participant.platform_submission_id,
                Participant.completion_code,
            )
        ).all()
    return {value for row in rows for value in row if value}


def minari_episodes(db: Database, tmp_path: Path) -> list[tuple[int, str, list[int]]]:
    study_file = tmp_path / "study.toml"
    study_file.write_text("title = 'x'\n")
    return [
        (episode.infos["participant"][0], episode.infos["worker"][0], list(episode.actions))
        for dataset in study_datasets(db, StudyFile.read(study_file))
        for episode in dataset.episodes
    ]


def test_a_scrub_leaves_no_raw_identifier_and_the_export_unchanged(
    client: TestClient, db: Database, study: StudyConfig, tmp_path: Path
) -> None:
    first = replica_worker(client, db, "WORKERONE", "a remark")
    second = replica_worker(client, db, "WORKERTWO", "another remark")
    for who in (first, second):
        paid = client.post(
            f"/api/admin/participants/{who}/bonuses",
            json={"amount": "0.25", "reason": "Thanks", "unique_token": f"bonus-token-{who}"},
            headers=ADMIN,
        )
        assert paid.status_code == 200, paid.text
    reviewed = client.post(
        f"/api/admin/participants/{first}/approval", json={"message": "Good"}, headers=ADMIN
    )
    assert reviewed.status_code == 200, reviewed.text
    wait_for_updates(db)
    raw = raw_identifiers(db)
    # Worker and assignment ids of both, and both completion codes.
    assert len(raw) == 6 and {"WORKERONE", "WORKERTWO"} <= raw
    text = text_in_database(db)
    assert all(value in text for value in raw)
    exported = export_tables(db)
    episodes = minari_episodes(db, tmp_path)
    url = db.engine.url.render_as_string(hide_password=False)

    # Nobody is idle for a day yet: nothing is scrubbed.
    assert main(["db", "scrub", "--database-url", url, "--older-than-days", "1"]) == 0
    assert raw_identifiers(db) == raw
    assert main(["db", "scrub", "--database-url", url]) == 0

    text = text_in_database(db)
    left = sorted(value for value in raw if value in text)
    assert left == []
    with db.read() as s:
        assert all(p.identifiers_scrubbed_at is not None for p in s.scalars(select(Participant)))
    after = export_tables(db)
    assert set(after) == set(exported)
    for name, frame in exported.items():
        assert after[name].equals(frame), name
    assert minari_episodes(db, tmp_path) == episodes
    # A second scrub changes nothing.
    before_again = text_in_database(db)
    assert main(["db", "scrub", "--database-url", url]) == 0
    assert text_in_database(db) == before_again

    # The experimenter can still erase a scrubbed participant by the worker id they give.
    assert main(["erase", "--database-url", url, "WORKERTWO", "--yes"]) == 0
    with db.read() as s:
        assert list(s.scalars(select(Participant.id))) == [first]


def test_the_server_scrubs_ids_past_the_study_s_days(client: TestClient, db: Database) -> None:
    arrived = client.post(
        "/api/arrivals",
        json={
            "assignmentId": "AOLD",
            "hitId": "H1",
            "workerId": "WOLD",
            "turkSubmitTo": "https://workersandbox.mturk.com",
        },
    )
    assert arrived.status_code == 201, arrived.text
    now = utcnow()
    assert scrub(db, older_than_days=30, now=now) == 0
    assert scrub(db, older_than_days=30, now=now + timedelta(days=31)) == 1
    assert raw_identifiers(db).isdisjoint({"WOLD", "AOLD"})


def test_bad_scrub_arguments_are_refused(db: Database, capsys: pytest.CaptureFixture[str]) -> None:
    url = db.engine.url.render_as_string(hide_password=False)
    assert main(["db", "scrub", "--database-url", url, "--older-than-days", "-1"]) == 2
    assert "--older-than-days must be 0 or more" in capsys.readouterr().err


def test_the_prolific_replica_s_rows_are_scrubbed_and_erased(
    client: TestClient, db: Database
) -> None:
    """The replica's rows hold a PROLIFIC_PID as text (``participant_id``) and in a bonus
    set-up's CSV. Erasure leaves them as they were: Prolific keeps its submission, its payment
    and its bonus set-up when a study erases a participant, so the replica does (our own rows
    name the participant no more). Scrubbing leaves no raw PID or SESSION_ID of a participant
    we still have anywhere."""
    from server.app.storage.replica_models import (
        ProlificReplicaBonusSetup,
        ProlificReplicaPayment,
        ProlificReplicaSubmission,
    )
    from tests.app.platforms.test_prolific import prolific_participant

    people = [prolific_participant(client, db) for _ in range(2)]
    for who, _, _ in people:
        paid = client.post(
            f"/api/admin/participants/{who}/bonuses",
            json={"amount": "0.40", "reason": "Thanks", "unique_token": f"bonus-token-{who}"},
            headers=ADMIN,
        )
        assert paid.status_code == 200, paid.text
    with db.read() as s:
        pids = {p.id: p.platform_participant_id for p in s.scalars(select(Participant))}
    (kept, kept_session, _), (erased, erased_session, erased_study) = people
    url = db.engine.url.render_as_string(hide_password=False)

    replica = {
        ProlificReplicaSubmission.__tablename__,
        ProlificReplicaPayment.__tablename__,
        ProlificReplicaBonusSetup.__tablename__,
    }
    before = {name: rows for name, rows in snapshot(db).items() if name in replica}
    assert main(["erase", "--database-url", url, str(erased), "--yes"]) == 0
    assert {name: rows for name, rows in snapshot(db).items() if name in replica} == before
    with db.read() as s:
        assert set(s.scalars(select(ProlificReplicaSubmission.id))) == {
            kept_session,
            erased_session,
        }
        assert set(s.scalars(select(ProlificReplicaPayment.participant_id))) == set(pids.values())
        setup = s.scalars(
            select(ProlificReplicaBonusSetup).where(
                ProlificReplicaBonusSetup.study_id == erased_study["id"]
            )
        ).one()
        (audit,) = s.scalars(select(Erasure))
    assert pids[erased] in setup.csv_bonuses
    assert not replica & set(audit.rows)  # the audit row counts only rows that went
    ours = text_in_database(db, leave_out=replica)
    assert pids[erased] not in ours and erased_session not in ours

    assert pids[kept] in text_in_database(db)
    assert main(["db", "scrub", "--database-url", url]) == 0
    text = text_in_database(db)
    assert pids[kept] not in text and kept_session not in text
    with db.read() as s:
        # The rows stay, the kept one's under pseudonyms: the replica still knows both.
        assert s.scalar(select(func.count()).select_from(ProlificReplicaSubmission)) == 2
        assert list(s.scalars(select(ProlificReplicaPayment.amount))) == [40, 40]
