"""A participant who declines consent on Prolific: their NO_CONSENT code (REQUEST_RETURN)
completes the submission (AWAITING REVIEW, ``return_requested`` set) and asks them to return it,
as Prolific does; it is RETURNED only if they do. The server records both times, from the poll
and from the webhook."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

import httpx
from fastapi.testclient import TestClient

from server.app.platforms.prolific import ProlificClient
from server.app.platforms.prolific_replica import ReplicaTransport
from server.app.platforms.prolific_sync import reconcile_submissions
from server.app.storage.db import Database
from server.app.storage.models import Participant
from server.app.storage.replica_models import ProlificReplicaSubmission
from tests.app.platforms.test_prolific import ADMIN, draft

# The server with BAM_PROLIFIC_WEBHOOK_SECRET set, and a study that finishes on Prolific.
from tests.app.platforms.test_prolific_sync import client as client
from tests.app.platforms.test_prolific_sync import send, status_change, teaching
from tests.app.platforms.test_prolific_sync import settings as settings
from tests.app.platforms.test_prolific_sync import study as study
from tests.support.server import ADMIN_TOKEN

TOKEN = {"Authorization": f"Token {ADMIN_TOKEN}"}
API = "/prolific/api/v1"


def published(http: TestClient | httpx.Client, places: int = 3, base: str | None = None) -> str:
    made = draft(places)
    if base is not None:
        made["external_study_url"] = (
            f"{base}/study?PROLIFIC_PID={{{{%PROLIFIC_PID%}}}}&STUDY_ID={{{{%STUDY_ID%}}}}"
            "&SESSION_ID={{%SESSION_ID%}}"
        )
    study_id = str(http.post(f"{API}/studies/", json=made, headers=TOKEN).json()["id"])
    started = http.post(
        f"{API}/studies/{study_id}/transition/", json={"action": "PUBLISH"}, headers=TOKEN
    )
    assert started.status_code == 200, started.text
    return study_id


def take_a_place(client: TestClient, study_id: str) -> tuple[str, str]:
    """A participant takes a place on the replica: (PROLIFIC_PID, SESSION_ID)."""
    sent = client.post(
        f"/prolific/studies/{study_id}/take-part", headers=ADMIN, follow_redirects=False
    )
    assert sent.status_code == 303, sent.text
    url = httpx.URL(sent.headers["location"])
    return url.params["PROLIFIC_PID"], url.params["SESSION_ID"]


def hand_in(client: TestClient, pid: str, code: str) -> httpx.Response:
    return client.get(
        "/prolific/submissions/complete",
        params={"cc": code},
        cookies={"prolific_replica_pid": pid},
    )


def replica_row(db: Database, submission: str) -> ProlificReplicaSubmission:
    with db.read() as s:
        row = s.get(ProlificReplicaSubmission, submission)
        assert row is not None
        return row


def ours(db: Database, participant: int) -> Participant:
    with db.read() as s:
        p = s.get(Participant, participant)
        assert p is not None
        return p


def listed(client: TestClient, participant: int) -> dict[str, Any]:
    rows = client.get("/api/admin/participants", headers=ADMIN).json()
    (row,) = [x for x in rows if x["participant_id"] == participant]
    return dict(row)


def test_no_consent_completes_the_submission_and_only_the_participant_returns_it(
    client: TestClient, db: Database
) -> None:
    """Not RETURNED at once: AWAITING REVIEW with return_requested (the place still held, as
    on Prolific); the participant's Return makes it RETURNED and frees the place."""
    study_id = published(client, places=2)
    pid, submission = take_a_place(client, study_id)
    landed = hand_in(client, pid, "NOCONSNT")
    assert landed.status_code == 200 and "AWAITING REVIEW" in landed.text
    assert "asked to return it" in landed.text

    seen = client.get(f"{API}/submissions/{submission}/", headers=TOKEN).json()
    assert seen["status"] == "AWAITING REVIEW" and seen["study_code"] == "NOCONSNT"
    assert seen["return_requested"] is not None
    assert seen["return_requested"] == seen["completed_at"]
    assert client.get(f"{API}/studies/{study_id}/", headers=TOKEN).json()["places_taken"] == 1
    # The completion code without REQUEST_RETURN asks for nothing.
    other_pid, other = take_a_place(client, study_id)
    assert hand_in(client, other_pid, "C1A2B3C4").status_code == 200
    assert replica_row(db, other).return_requested is None
    page = client.get("/prolific", headers=ADMIN)
    assert page.text.count("data-return-requested") == 1

    # Prolific times out only an active submission; a completed one the participant returns.
    timed_out = client.post(f"/prolific/submissions/{submission}/time-out", headers=ADMIN)
    assert timed_out.status_code == 409 and "AWAITING REVIEW" in timed_out.text
    returned = client.post(
        f"/prolific/submissions/{submission}/return", headers=ADMIN, follow_redirects=False
    )
    assert returned.status_code == 303, returned.text
    after = client.get(f"{API}/submissions/{submission}/", headers=TOKEN).json()
    assert after["status"] == "RETURNED"
    assert after["return_requested"] == seen["return_requested"]  # Prolific keeps it
    assert client.get(f"{API}/studies/{study_id}/", headers=TOKEN).json()["places_taken"] == 1
    again = client.post(f"/prolific/submissions/{submission}/return", headers=ADMIN)
    assert again.status_code == 409 and "RETURNED" in again.text


def test_the_poll_records_prolifics_completion_and_return_request(
    client: TestClient, db: Database
) -> None:
    study_id = published(client)
    pid, submission = take_a_place(client, study_id)
    participant = teaching(db, pid, submission, study_id, status="declined")
    hand_in(client, pid, "NOCONSNT")
    prolific = ProlificClient(
        "http://replica/prolific/api/v1", ADMIN_TOKEN, transport=ReplicaTransport(db, ADMIN_TOKEN)
    )
    assert reconcile_submissions(db, prolific, study_id) == {submission: "AWAITING REVIEW"}
    row, p = replica_row(db, submission), ours(db, participant)
    assert p.platform_status == "AWAITING REVIEW"
    assert row.return_requested is not None
    assert p.platform_return_requested_at == row.return_requested
    assert p.platform_completed_at == row.completed_at
    assert row.completed_at is not None

    # They return it: RETURNED, still "declined" on our side, the request kept, nothing due.
    client.post(f"/prolific/submissions/{submission}/return", headers=ADMIN)
    reconcile_submissions(db, prolific, study_id)
    p = ours(db, participant)
    assert (p.status, p.platform_status) == ("declined", "RETURNED")
    assert p.platform_return_requested_at == row.return_requested


def test_the_webhook_records_a_decliners_completion_as_a_return_request(
    client: TestClient, db: Database
) -> None:
    """The webhook's body has the status only: the event's time is when the submission was
    completed and, for a participant our page sent back with NO_CONSENT, asked to return."""
    decliner = teaching(db, "1" * 24, "2" * 24, status="declined")
    finisher = teaching(db, "3" * 24, "4" * 24, status="submitted")
    happened = datetime(2026, 11, 20, 9, 30, tzinfo=UTC)
    for n, submission in enumerate(("2" * 24, "4" * 24)):
        event = status_change("AWAITING REVIEW", submission)
        answer = send(client, event, f"ev-{n}", happened=happened.isoformat())
        assert answer.json()["result"] == "applied", answer.text
    p, q = ours(db, decliner), ours(db, finisher)
    assert (p.platform_completed_at, p.platform_return_requested_at) == (happened, happened)
    assert (q.platform_completed_at, q.platform_return_requested_at) == (happened, None)
