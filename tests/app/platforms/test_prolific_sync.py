"""Prolific's submission statuses kept in step: the signed webhook (a forged, unsigned, altered
or old request changes nothing; a redelivered event is applied once) and the poll of the
study's submissions; a RETURNED or TIMED-OUT participant is released, their data kept."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from datetime import UTC, datetime
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from server.app.export.tables import export_tables
from server.app.main import create_app
from server.app.platforms.prolific import ProlificClient
from server.app.platforms.prolific_replica import ReplicaTransport
from server.app.platforms.prolific_sync import (
    WebhookRefused,
    event_time,
    reconcile_submissions,
    signature,
    verify,
)
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import Participant, StatusChange
from server.app.study_file import StudyConfig
from tests.app.platforms.test_prolific import ADMIN, draft
from tests.support.server import ADMIN_TOKEN, live, make_settings, study_config
from tests.support.server import Participant as Participant_

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


def teaching(
    db: Database, pid: str, submission: str, study_id: str = "a" * 24, status: str = "teaching"
) -> int:
    with db.write() as s:
        p = Participant(
            token_hash=os.urandom(32).hex(),
            platform="prolific",
            platform_participant_id=pid,
            platform_submission_id=submission,
            platform_study_id=study_id,
            status=status,
        )
        s.add(p)
        s.flush()
        return p.id


def status_change(status: str, submission: str = "c" * 24) -> dict[str, Any]:
    """Prolific's ``submission.status.change`` body for a submission of study a...a."""
    return {
        "event_type": "submission.status.change",
        "resource_id": submission,
        "study_id": "a" * 24,
        "status": status,
    }


def status_of(db: Database, participant: int) -> tuple[str, str | None]:
    with db.read() as s:
        p = s.get(Participant, participant)
        assert p is not None
        return p.status, p.platform_status


def send(
    client: TestClient,
    payload: dict[str, Any],
    event_id: str,
    *,
    secret: str = SECRET,
    at: int | None = None,
    alter: bool = False,
    happened: str | None = None,
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
            **({} if happened is None else {"X-Timestamp": happened}),
        },
    )


def test_only_a_genuine_fresh_webhook_releases_a_returned_participant_once(
    client: TestClient, db: Database
) -> None:
    participant = teaching(db, "b" * 24, "c" * 24)
    event = status_change("RETURNED")
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
    # The dashboard shows Prolific's status; the export keeps the participant, marked with it.
    listed = client.get("/api/admin/participants", headers=ADMIN).json()
    assert [(x["status"], x["prolific_status"]) for x in listed] == [("returned", "RETURNED")]
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
    # The same poll from the admin API (the server's own client, on the replica here).
    answer = client.post(
        "/api/admin/reconciliation", params={"prolific_study": study["id"]}, headers=ADMIN
    )
    assert answer.status_code == 200 and answer.json()["prolific_statuses"] == seen


@pytest.fixture
def study() -> StudyConfig:
    return study_config(
        completion={
            "mode": "prolific",
            "prolific_code": "C1A2B3C4",
            "prolific_no_consent_code": "NOCONSNT",
        }
    )


def test_a_released_participant_who_comes_back_sees_a_clear_page_and_changes_nothing(
    client: TestClient, db: Database
) -> None:
    link = {"PROLIFIC_PID": "e" * 24, "STUDY_ID": "a" * 24, "SESSION_ID": "f" * 24}
    arrived = client.post("/api/arrivals", json=link)
    assert arrived.status_code == 201, arrived.text
    participant = Participant_(client, arrived.json()["token"])
    participant.act("/api/participant/consent", agree=True)
    event = status_change("TIMED-OUT", "f" * 24)
    assert send(client, event, "ev-timeout-1").json()["result"] == "applied"
    with db.read() as s:
        (ours,) = s.scalars(select(Participant.id))
    assert status_of(db, ours) == ("returned", "TIMED-OUT")
    # Coming back by the same link: a page that says why, and the release stands.
    again = client.post("/api/arrivals", json=link)
    assert again.status_code == 403 and "returned or that its time ran out" in again.text
    page = client.get("/study", params=link)
    assert "This study has ended for you" in page.text
    refused = client.post(
        "/api/participant/start", json={"seq": participant.seq}, headers=participant.headers
    )
    assert refused.status_code == 409 and "place has gone to another participant" in refused.text
    assert status_of(db, ours) == ("returned", "TIMED-OUT")


def test_the_replica_sends_signed_webhooks_that_release_a_returning_participant(
    db: Database, settings: Settings, study: StudyConfig, executor: ProcessPoolExecutor
) -> None:
    app = create_app(settings, study, db=db, executor=executor)
    token = {"Authorization": f"Token {ADMIN_TOKEN}"}
    with live(app) as base, httpx.Client(base_url=base, headers=ADMIN) as browser:
        made = draft(2)
        made["external_study_url"] = (
            f"{base}/study?PROLIFIC_PID={{{{%PROLIFIC_PID%}}}}&STUDY_ID={{{{%STUDY_ID%}}}}"
            "&SESSION_ID={{%SESSION_ID%}}"
        )
        created = browser.post("/prolific/api/v1/studies/", json=made, headers=token).json()
        browser.post(
            f"/prolific/api/v1/studies/{created['id']}/transition/",
            json={"action": "PUBLISH"},
            headers=token,
        )
        # The participant takes part: the replica sends them to the study, which lets them in.
        entered = browser.post(
            f"/prolific/studies/{created['id']}/take-part", follow_redirects=True
        )
        assert entered.status_code == 200 and entered.url.path == "/study", entered.url
        with db.read() as s:
            (ours,) = s.scalars(select(Participant.id))
            submission = s.scalar(select(Participant.platform_submission_id))
        browser.post(f"/prolific/submissions/{submission}/return")
        deadline = time.monotonic() + 60
        while status_of(db, ours) != ("returned", "RETURNED"):
            assert time.monotonic() < deadline, status_of(db, ours)
            time.sleep(0.1)


def test_a_prolific_participant_who_declines_consent_is_sent_back_with_no_consent(
    client: TestClient, db: Database
) -> None:
    link = {"PROLIFIC_PID": "1" * 24, "STUDY_ID": "a" * 24, "SESSION_ID": "2" * 24}
    participant = Participant_(client, client.post("/api/arrivals", json=link).json()["token"])
    declined = participant.act("/api/participant/consent", agree=False)["participant"]
    assert declined["status"] == "declined"
    assert declined["completion"] == {
        **declined["completion"],
        "code": "NOCONSNT",
        "mode": "prolific",
        "redirect_url": "https://app.prolific.com/submissions/complete?cc=NOCONSNT",
    }


@pytest.mark.parametrize("timestamp", ["²³", "1" * 400, "9" * 5000, "-5", " 17", "1.5e9"])
def test_a_webhook_timestamp_that_is_not_a_unix_time_is_refused_not_raised(
    timestamp: str,
) -> None:
    """Refused as a forgery (401), never an error of ours (500): superscript digits pass
    ``str.isdigit`` and fail ``int``; hundreds of digits overflow a float."""
    with pytest.raises(WebhookRefused, match="not a UNIX time"):
        verify(SECRET, timestamp, signature(SECRET, timestamp, b"{}"), b"{}")


def test_a_time_out_or_return_releases_only_who_is_still_working(
    client: TestClient, db: Database
) -> None:
    """Prolific lets a participant past the time limit finish: one who completed or submitted
    keeps that status (reviewable, paid if approved), marked TIMED-OUT; one still teaching
    is released."""
    ids = {
        status: teaching(db, f"{n}" * 24, f"{n + 4}" * 24, status=status)
        for n, status in enumerate(("teaching", "completed", "submitted"), start=1)
    }
    for n in range(1, len(ids) + 1):
        event = status_change("TIMED-OUT", f"{n + 4}" * 24)
        assert send(client, event, f"ev-{n}").json()["result"] == "applied"
    assert status_of(db, ids["teaching"]) == ("returned", "TIMED-OUT")
    assert status_of(db, ids["completed"]) == ("completed", "TIMED-OUT")
    assert status_of(db, ids["submitted"]) == ("submitted", "TIMED-OUT")
    with db.read() as s:
        released = set(s.scalars(select(StatusChange.participant_id)))
    assert released == {ids["teaching"]}


def test_an_event_whose_effect_failed_is_applied_when_redelivered(
    db: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The event's id and the status change commit together: a crash between the two leaves
    no id behind, so Prolific's redelivery of the same id releases the participant."""
    from server.app.platforms import prolific_sync

    participant = teaching(db, "b" * 24, "c" * 24)
    event = status_change("RETURNED")

    def crash(*args: Any) -> bool:
        raise RuntimeError("the server died after recording the event")

    with monkeypatch.context() as patched:
        patched.setattr(prolific_sync, "_apply_status", crash)
        with pytest.raises(RuntimeError):
            prolific_sync.apply_webhook(db, "ev-1", event)
    assert status_of(db, participant) == ("teaching", None)
    assert prolific_sync.apply_webhook(db, "ev-1", event) == "applied"
    assert status_of(db, participant) == ("returned", "RETURNED")
    assert prolific_sync.apply_webhook(db, "ev-1", event) == "already applied"


@pytest.mark.parametrize("status", ["PROCESSING", "UNKNOWN"])
def test_a_transient_status_is_answered_and_keeps_the_submissions_status(
    client: TestClient, db: Database, status: str
) -> None:
    participant = teaching(db, "b" * 24, "c" * 24)
    event = status_change("AWAITING REVIEW")
    assert send(client, event, "ev-1").json()["result"] == "applied"
    answered = send(client, {**event, "status": status}, "ev-2")
    assert answered.status_code == 200 and "transient" in answered.json()["result"]
    assert status_of(db, participant) == ("teaching", "AWAITING REVIEW")
    refused = send(client, {**event, "status": "LOST"}, "ev-3")
    assert refused.status_code == 400 and "LOST" in refused.text
    # A refused event leaves no id: sent again with a known status, it is applied.
    assert send(client, event | {"status": "APPROVED"}, "ev-3").json()["result"] == "applied"


def test_an_event_older_than_the_status_stored_leaves_it(client: TestClient, db: Database) -> None:
    """Prolific's events can arrive out of order; ``X-Timestamp`` says when each happened. The
    approval (later) arrives first; the completion (earlier) then changes nothing."""
    participant = teaching(db, "b" * 24, "c" * 24, status="submitted")
    event = status_change("AWAITING REVIEW")
    approved = send(client, {**event, "status": "APPROVED"}, "ev-2", happened="1700000200")
    assert approved.json()["result"] == "applied"
    late = send(
        client, {**event, "status": "AWAITING REVIEW"}, "ev-1", happened="2023-11-14T22:13:20Z"
    )
    assert late.status_code == 200 and "older" in late.json()["result"]
    assert status_of(db, participant) == ("submitted", "APPROVED")
    # A newer one applies.
    newer = send(client, {**event, "status": "RETURNED"}, "ev-3", happened="1700000300.5")
    assert newer.json()["result"] == "applied"
    assert status_of(db, participant) == ("submitted", "RETURNED")


@pytest.mark.parametrize(
    ("header", "expected"),
    [
        ("1700000000", datetime(2023, 11, 14, 22, 13, 20, tzinfo=UTC)),
        ("1700000000.25", datetime(2023, 11, 14, 22, 13, 20, 250000, tzinfo=UTC)),
        ("2023-11-14T22:13:20Z", datetime(2023, 11, 14, 22, 13, 20, tzinfo=UTC)),
        ("2023-11-14T23:13:20+01:00", datetime(2023, 11, 14, 22, 13, 20, tzinfo=UTC)),
        ("2023-11-14T22:13:20", datetime(2023, 11, 14, 22, 13, 20, tzinfo=UTC)),
        ("yesterday", None),
        ("9" * 30, None),
        ("²³", None),
        ("", None),
        (None, None),
    ],
)
def test_the_events_time_is_read_from_unix_seconds_or_iso_8601(
    header: str | None, expected: datetime | None
) -> None:
    assert event_time(header) == expected
