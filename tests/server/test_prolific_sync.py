"""Prolific's submission statuses kept in step: the signed webhook (a forged, unsigned, altered
or old request changes nothing; a redelivered event is applied once) and the poll of the
study's submissions; a RETURNED or TIMED-OUT participant is released, their data kept."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from server.app.config import StudyConfig
from server.app.main import create_app
from server.app.platforms.prolific import ProlificClient
from server.app.platforms.prolific_replica import ReplicaTransport
from server.app.platforms.prolific_sync import reconcile_submissions, signature
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import Participant, StatusChange
from tests.server.conftest import ADMIN_TOKEN, make_settings
from tests.server.test_prolific import ADMIN, draft

SECRET = "d2ViaG9vay1zZWNyZXQtZm9yLXRlc3Rz"


@pytest.fixture
def settings(db: Database) -> Settings:
    return make_settings(
        db.engine.url.render_as_string(hide_password=False), prolific_webhook_secret=SECRET
    )


@pytest.fixture
def client(
    db: Database, settings: Settings, study: StudyConfig, executor: ProcessPoolExecutor
) -> Iterator[TestClient]:
    with TestClient(create_app(settings, study, db=db, executor=executor)) as test_client:
        yield test_client


def teaching(db: Database, pid: str, submission: str, study_id: str = "a" * 24) -> int:
    with db.write() as s:
        p = Participant(
            token_hash=os.urandom(32).hex(),
            platform="prolific",
            worker_id=pid,
            assignment_id=submission,
            hit_id=study_id,
            status="teaching",
        )
        s.add(p)
        s.flush()
        return p.id


def status_of(db: Database, participant: int) -> tuple[str, str | None]:
    with db.read() as s:
        p = s.get(Participant, participant)
        assert p is not None
        return p.status, p.prolific_status


def send(
    client: TestClient,
    payload: dict[str, Any],
    event_id: str,
    *,
    secret: str = SECRET,
    at: int | None = None,
    alter: bool = False,
) -> httpx.Response:
    body = json.dumps(payload).encode()
    stamp = str(int(time.time()) if at is None else at)
    signed = signature(secret, stamp, body)
    if alter:
        body = body.replace(b"RETURNED", b"APPROVED")
    return client.post(
        "/prolific/webhook",
        content=body,
        headers={
            "Content-Type": "application/json",
            "X-Prolific-Request-Signature": signed,
            "X-Prolific-Request-Timestamp": stamp,
            "X-Event-ID": event_id,
        },
    )


def test_only_a_genuine_fresh_webhook_releases_a_returned_participant_once(
    client: TestClient, db: Database
) -> None:
    participant = teaching(db, "b" * 24, "c" * 24)
    event = {
        "event_type": "submission.status.change",
        "resource_id": "c" * 24,
        "study_id": "a" * 24,
        "status": "RETURNED",
    }
    refusals = [
        send(client, event, "ev-1", secret="not-the-secret"),
        send(client, event, "ev-1", at=int(time.time()) - 3600),
        send(client, event, "ev-1", alter=True),
        client.post("/prolific/webhook", json=event, headers={"X-Event-ID": "ev-1"}),
    ]
    assert [r.status_code for r in refusals] == [401, 401, 401, 401]
    assert "replay" in refusals[1].text and "signature" in refusals[0].text
    assert status_of(db, participant) == ("teaching", None)

    applied = send(client, event, "ev-1")
    assert applied.status_code == 200 and applied.json()["result"] == "applied"
    assert status_of(db, participant) == ("returned", "RETURNED")
    # Redelivered (at-least-once): applied once; the status history has one release.
    assert send(client, event, "ev-1").json()["result"] == "already applied"
    with db.read() as s:
        notes = list(
            s.scalars(select(StatusChange.note).where(StatusChange.participant_id == participant))
        )
    assert len(notes) == 1 and "RETURNED" in (notes[0] or "")
    # The export keeps the participant, marked with Prolific's status.
    from server.app.export.tables import export_tables

    row = export_tables(db)["participants"].set_index("participant_id").loc[participant]
    assert row["status"] == "returned" and row["prolific_status"] == "RETURNED"


def test_the_poll_releases_returned_and_timed_out_participants(
    client: TestClient, db: Database
) -> None:
    token = {"Authorization": f"Token {ADMIN_TOKEN}"}
    study = client.post("/prolific/api/v1/studies/", json=draft(5), headers=token).json()
    client.post(
        f"/prolific/api/v1/studies/{study['id']}/transition/",
        json={"action": "PUBLISH"},
        headers=token,
    )
    ours = {}
    for _ in range(3):
        sent = client.post(
            f"/prolific/studies/{study['id']}/take-part", headers=ADMIN, follow_redirects=False
        )
        url = httpx.URL(sent.headers["location"])
        submission = url.params["SESSION_ID"]
        ours[submission] = teaching(db, url.params["PROLIFIC_PID"], submission, study["id"])
    kept, returned, timed_out = list(ours)
    client.post(f"/prolific/submissions/{returned}/return", headers=ADMIN)
    client.post(f"/prolific/submissions/{timed_out}/time-out", headers=ADMIN)
    prolific = ProlificClient(
        "http://replica/prolific/api/v1",
        ADMIN_TOKEN,
        transport=ReplicaTransport(db, ADMIN_TOKEN),
    )
    seen = reconcile_submissions(db, prolific, study["id"])
    assert seen == {kept: "ACTIVE", returned: "RETURNED", timed_out: "TIMED-OUT"}
    assert status_of(db, ours[kept]) == ("teaching", "ACTIVE")
    assert status_of(db, ours[returned]) == ("returned", "RETURNED")
    assert status_of(db, ours[timed_out]) == ("returned", "TIMED-OUT")
