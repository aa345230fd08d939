"""A participant who declines consent on Prolific: their NO_CONSENT code (REQUEST_RETURN)
completes the submission (AWAITING REVIEW, ``return_requested`` set) and asks them to return it,
as Prolific does; it is RETURNED only if they do. The server records both times (poll and
webhook), the dashboard flags the decliner who has not returned and shows when Prolific would
approve and pay the submission by itself (21 days after its completion), with a warning in the
last week, and the decliner, like a finisher whose submission timed out, can be reviewed."""

from __future__ import annotations

import time
from concurrent.futures import ProcessPoolExecutor
from datetime import UTC, datetime, timedelta
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from server.app.export.tables import export_tables
from server.app.main import create_app
from server.app.platforms.prolific import ProlificClient
from server.app.platforms.prolific_replica import ReplicaTransport
from server.app.platforms.prolific_sync import reconcile_submissions
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import Participant
from server.app.storage.replica_models import ProlificReplicaSubmission
from server.app.study_file import StudyConfig
from tests.app.platforms.test_prolific import ADMIN, REASON, draft

# The server with BAM_PROLIFIC_WEBHOOK_SECRET set, and a study that finishes on Prolific.
from tests.app.platforms.test_prolific_sync import client as client
from tests.app.platforms.test_prolific_sync import send, status_change, teaching
from tests.app.platforms.test_prolific_sync import settings as settings
from tests.app.platforms.test_prolific_sync import study as study
from tests.support.server import ADMIN_TOKEN, live
from tests.support.server import Participant as Participant_

DECIDED = {"approval": "approved", "rejection": "rejected"}
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
    assert "asks you to return it" in landed.text

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
    shown = listed(client, participant)
    assert shown["awaits_decision"] is True
    assert shown["return_requested_at"] is not None
    assert datetime.fromisoformat(shown["auto_approval_at"]) == row.completed_at + timedelta(
        days=21
    )
    assert shown["auto_approval_soon"] is False

    # The export keeps both times, for the decliners who never returned.
    exported = export_tables(db)["participants"].set_index("participant_id").loc[participant]
    assert exported["prolific_return_requested_at"] == row.return_requested.isoformat()
    assert exported["prolific_completed_at"] == row.completed_at.isoformat()

    # They return it: RETURNED, still "declined" on our side, the request kept, nothing due.
    client.post(f"/prolific/submissions/{submission}/return", headers=ADMIN)
    reconcile_submissions(db, prolific, study_id)
    p = ours(db, participant)
    assert (p.status, p.platform_status) == ("declined", "RETURNED")
    assert p.platform_return_requested_at == row.return_requested
    shown = listed(client, participant)
    assert (shown["awaits_decision"], shown["auto_approval_at"]) == (False, None)
    refused = client.post(f"/api/admin/participants/{participant}/approval", json={}, headers=ADMIN)
    assert refused.status_code == 409 and "Prolific's RETURNED" in refused.text


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


def test_the_dashboard_warns_a_week_before_prolific_approves_by_itself(
    client: TestClient, db: Database
) -> None:
    """21 days after completion; the warning from 7 days before, in the JSON and on the page."""
    now = datetime.now(UTC).replace(microsecond=0)
    ages = {"fresh": 2, "due soon": 15, "awaiting, no time": None}
    ids = {}
    for n, (name, days) in enumerate(ages.items(), start=1):
        ids[name] = teaching(db, f"{n}" * 24, f"{n + 5}" * 24, status="submitted")
        with db.write() as s:
            p = s.get(Participant, ids[name])
            assert p is not None
            p.platform_status = "AWAITING REVIEW"
            p.platform_completed_at = None if days is None else now - timedelta(days=days)
    shown = {name: listed(client, ids[name]) for name in ages}
    assert datetime.fromisoformat(shown["fresh"]["auto_approval_at"]) == now + timedelta(days=19)
    assert shown["fresh"]["auto_approval_soon"] is False
    assert datetime.fromisoformat(shown["due soon"]["auto_approval_at"]) == now + timedelta(days=6)
    assert shown["due soon"]["auto_approval_soon"] is True
    assert shown["awaiting, no time"]["auto_approval_at"] is None
    # Decided: Prolific approves nothing by itself any more.
    with db.write() as s:
        p = s.get(Participant, ids["due soon"])
        assert p is not None
        p.platform_status = "APPROVED"
    assert listed(client, ids["due soon"])["auto_approval_at"] is None


@pytest.mark.parametrize("decision", ["approval", "rejection"])
def test_a_decliner_who_never_returns_is_reviewed_through_the_replica(
    db: Database,
    settings: Settings,
    study: StudyConfig,
    executor: ProcessPoolExecutor,
    decision: str,
) -> None:
    """Over real HTTP: the participant declines, goes back with NO_CONSENT, the replica's signed
    webhook tells the server, the dashboard flags them and reviews them like anyone else."""
    app = create_app(settings, study, db=db, executor=executor)
    with live(app) as base, httpx.Client(base_url=base, headers=ADMIN, timeout=60) as browser:
        study_id = published(browser, base=base)
        sent = browser.post(f"/prolific/studies/{study_id}/take-part")
        link = dict(httpx.URL(sent.headers["location"]).params)
        arrived = browser.post("/api/arrivals", json=link)
        assert arrived.status_code == 201, arrived.text
        person = Participant_(browser, arrived.json()["token"])
        declined = person.act("/api/participant/consent", agree=False)["participant"]
        landed = browser.get(declined["completion"]["redirect_url"])
        assert landed.status_code == 200 and "AWAITING REVIEW" in landed.text
        participant = int(person.get("/api/participant")["participant_id"])

        deadline = time.monotonic() + 60
        while ours(db, participant).platform_status != "AWAITING REVIEW":
            assert time.monotonic() < deadline, ours(db, participant).platform_status
            time.sleep(0.1)
        p = ours(db, participant)
        assert p.status == "declined" and p.platform_return_requested_at is not None
        row = browser.get("/api/admin/participants").json()[0]
        assert row["awaits_decision"] is True and row["return_requested_at"] is not None
        assert row["auto_approval_at"] is not None and row["auto_approval_soon"] is False

        body = (
            {} if decision == "approval" else {"message": REASON, "rejection_category": "NO_DATA"}
        )
        answer = browser.post(f"/api/admin/participants/{participant}/{decision}", json=body)
        assert answer.status_code == 200, answer.text
        expected = "APPROVED" if decision == "approval" else "REJECTED"
        assert answer.json()["prolific_status"] == expected
        assert answer.json()["review"]["decision"] == DECIDED[decision]
        with db.read() as s:
            status = s.scalar(
                select(ProlificReplicaSubmission.status).where(
                    ProlificReplicaSubmission.id == link["SESSION_ID"]
                )
            )
        assert status == expected


def test_a_finisher_whose_submission_timed_out_can_be_approved_not_rejected(
    client: TestClient, db: Database
) -> None:
    """Prolific lets a timed-out submission be approved (which pays a participant who finished
    past the limit); it has nothing to reject."""
    study_id = published(client)
    pid, submission = take_a_place(client, study_id)
    participant = teaching(db, pid, submission, study_id, status="completed")
    client.post(f"/prolific/submissions/{submission}/time-out", headers=ADMIN)
    prolific = ProlificClient(
        "http://replica/prolific/api/v1", ADMIN_TOKEN, transport=ReplicaTransport(db, ADMIN_TOKEN)
    )
    reconcile_submissions(db, prolific, study_id)
    assert (ours(db, participant).status, ours(db, participant).platform_status) == (
        "completed",
        "TIMED-OUT",
    )
    assert listed(client, participant)["awaits_decision"] is True
    rejected = client.post(
        f"/api/admin/participants/{participant}/rejection",
        json={"message": REASON, "rejection_category": "NO_DATA"},
        headers=ADMIN,
    )
    assert rejected.status_code == 409 and "TIMED-OUT cannot be rejected" in rejected.text
    assert (
        client.get(f"/api/admin/participants/{participant}", headers=ADMIN).json()["review"] is None
    )
    approved = client.post(
        f"/api/admin/participants/{participant}/approval", json={}, headers=ADMIN
    )
    assert approved.status_code == 200, approved.text
    assert approved.json()["prolific_status"] == "APPROVED"
    assert replica_row(db, submission).status == "APPROVED"
    # A bonus is for submitted work only: this participant never reported a submission.
    bonus = client.post(
        f"/api/admin/participants/{participant}/bonuses",
        json={"amount": "1.00", "reason": "Thanks", "unique_token": "t" * 16},
        headers=ADMIN,
    )
    assert bonus.status_code == 409 and "has not submitted" in bonus.text


def test_a_submission_the_participant_returned_is_not_reviewed(
    client: TestClient, db: Database
) -> None:
    """Returned after submitting ("Return and cancel reward"): nothing to approve from here
    (Prolific would pay it as an extra participant), and nothing is recorded."""
    participant = teaching(db, "5" * 24, "6" * 24, status="submitted")
    assert send(client, status_change("RETURNED", "6" * 24), "ev-r").json()["result"] == "applied"
    assert listed(client, participant)["awaits_decision"] is False
    refused = client.post(f"/api/admin/participants/{participant}/approval", json={}, headers=ADMIN)
    assert refused.status_code == 409 and "is RETURNED on Prolific" in refused.text
    assert (
        client.get(f"/api/admin/participants/{participant}", headers=ADMIN).json()["review"] is None
    )
