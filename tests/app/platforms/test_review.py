"""Review of submitted work from the dashboard: approvals, rejections and bonuses go to the
review backend (the local MTurk replica here, shown on its HIT page), are stored once and
exported; bad requests are refused with a clear 4xx and store nothing. boto3's MTurk client
plugs in through ``MTurkClientBackend``, checked against a recording fake."""

from __future__ import annotations

import sys
import types
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from server.app.errors import ApiError
from server.app.export.files import dictionary_frame
from server.app.export.tables import export_tables
from server.app.platforms.backends import make_backend
from server.app.platforms.mturk import MTurkClientBackend, MTurkReplicaBackend
from server.app.platforms.review import Reviewed, ReviewRefused, ReviewUnavailable
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import Bonus, Review
from server.app.storage.replica_models import ReplicaAssignment, ReplicaBonus
from server.app.study_file import StudyConfig
from tests.support.server import (
    ADMIN_TOKEN,
    Participant,
    demonstrate_each_task,
    study_config,
    teaching_participant,
)

ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
BASE = "/api/admin/participants"


@pytest.fixture
def study() -> StudyConfig:
    """One agent, no tutorial: a participant submits after a few requests."""
    return study_config(
        learners=["cloning"],
        domains=[{"name": "navigation", "environments": ["wall"]}],
        tutorial={"enabled": False},
    )


def submitted_worker(client: TestClient, db: Database, worker: str) -> int:
    """A worker who accepts the replica's HIT, does the study and submits it as the page does
    (the study records the submission, the form posts to the replica); the participant id."""
    accepted = client.post(
        "/mturk/accept", data={"workerId": worker}, headers=ADMIN, follow_redirects=False
    )
    assert accepted.status_code == 303, accepted.text
    with db.read() as s:
        row = s.scalars(
            select(ReplicaAssignment).where(ReplicaAssignment.worker_id == worker)
        ).one()
        assignment, hit = row.assignment_id, row.hit_id
    arrived = client.post(
        "/api/arrivals",
        json={
            "assignmentId": assignment,
            "hitId": hit,
            "workerId": worker,
            "turkSubmitTo": "http://testserver",
        },
    )
    assert arrived.status_code == 201, arrived.text
    participant = Participant(client, arrived.json()["token"])
    participant.act("/api/participant/consent", agree=True)
    session_id = participant.act("/api/participant/start")["participant"]["current_session_id"]
    demonstrate_each_task(participant, session_id)
    done = participant.act(f"/api/sessions/{session_id}/finish")["participant"]
    assert done["status"] == "completed"
    participant.act("/api/participant/submission")
    posted = client.post(
        "/mturk/externalSubmit",
        data=done["completion"]["submit_fields"],
        headers=ADMIN,
    )
    assert posted.status_code == 200, posted.text
    return int(participant.get("/api/participant")["participant_id"])


def counts(db: Database) -> tuple[int, int, int, list[str]]:
    """Rows of the study's reviews and bonuses, the replica's bonuses, and its statuses."""
    with db.read() as s:
        return (
            int(s.scalar(select(func.count()).select_from(Review)) or 0),
            int(s.scalar(select(func.count()).select_from(Bonus)) or 0),
            int(s.scalar(select(func.count()).select_from(ReplicaBonus)) or 0),
            list(s.scalars(select(ReplicaAssignment.status).order_by(ReplicaAssignment.id))),
        )


def test_approve_reject_and_bonus_show_on_the_replica_and_in_the_export(
    client: TestClient, db: Database
) -> None:
    first = submitted_worker(client, db, "WORKER1")
    second = submitted_worker(client, db, "WORKER2")
    assert counts(db) == (0, 0, 0, ["submitted", "submitted"])

    approved = client.post(f"{BASE}/{first}/approval", json={"message": "Thank you"}, headers=ADMIN)
    assert approved.status_code == 200, approved.text
    assert approved.json()["review"]["decision"] == "approved"
    assert approved.json()["review"]["backend"] == "mturk-replica"
    rejected = client.post(
        f"{BASE}/{second}/rejection", json={"message": "No agent was taught"}, headers=ADMIN
    )
    assert rejected.status_code == 200, rejected.text
    assert rejected.json()["review"] == {
        **rejected.json()["review"],
        "decision": "rejected",
        "message": "No agent was taught",
    }
    bonus = {"amount": "1.50", "reason": "Taught every task", "unique_token": "bonus-token-1"}
    paid = client.post(f"{BASE}/{first}/bonuses", json=bonus, headers=ADMIN)
    assert paid.status_code == 200, paid.text
    assert [(b["amount"], b["reason"]) for b in paid.json()["bonuses"]] == [
        ("1.50", "Taught every task")
    ]
    # A retry of the same request (same token) answers the same and pays nothing more.
    again = client.post(f"{BASE}/{first}/bonuses", json=bonus, headers=ADMIN)
    assert again.status_code == 200 and again.json()["bonuses"] == paid.json()["bonuses"]
    # A second bonus with its own token is a second payment; a number is taken as well.
    more = {"amount": 0.25, "reason": "Extra", "unique_token": "bonus-token-2"}
    assert client.post(f"{BASE}/{first}/bonuses", json=more, headers=ADMIN).status_code == 200
    assert counts(db) == (2, 2, 2, ["approved", "rejected"])

    # The replica's HIT page shows the decisions and the bonuses.
    page = client.get("/mturk", headers=ADMIN).text
    assert page.count('data-status="approved"') == 1 and page.count('data-status="rejected"') == 1
    assert "No agent was taught" in page
    assert 'data-amount="1.50"' in page and 'data-amount="0.25"' in page
    assert "bonus-token-1" in page

    # The export records them, pseudonymised like participants.csv, and documents them.
    tables = export_tables(db)
    participants = tables["participants"].set_index("participant_id")
    reviews = tables["reviews"]
    assert list(reviews["decision"]) == ["approved", "rejected"]
    assert list(reviews["platform_submission_id"]) == [
        participants.loc[first, "platform_submission_id"],
        participants.loc[second, "platform_submission_id"],
    ]
    assert all(value.startswith("w_") for value in reviews["platform_participant_id"])
    bonuses = tables["bonuses"]
    assert list(bonuses["amount"]) == ["1.50", "0.25"]
    assert set(bonuses["payment_state"]) == {"paid"} and set(bonuses["currency"]) == {"USD"}
    assert list(bonuses["participant_id"]) == [first, first]
    plain = export_tables(db, pseudonymize=False)
    assert list(plain["bonuses"]["platform_participant_id"]) == ["WORKER1", "WORKER1"]
    dictionary = dictionary_frame()
    for name in ("reviews", "bonuses"):
        described = dictionary[dictionary["file"] == f"{name}.csv"]
        assert set(tables[name].columns) <= set(described["column"])
        assert described["description"].str.len().min() > 0


def test_bad_review_requests_are_refused_and_store_nothing(
    client: TestClient, db: Database
) -> None:
    done = submitted_worker(client, db, "WORKER1")
    working, _ = teaching_participant(client, "WORKER9", "ASSIGNMENT9")
    working_id = working.get("/api/participant")["participant_id"]
    bonus = {"amount": "2.00", "reason": "Good work", "unique_token": "token-0001"}

    def refused(path: str, body: dict[str, Any], status: int, words: str) -> None:
        before = counts(db)
        response = client.post(path, json=body, headers=ADMIN)
        assert response.status_code == status, (path, body, response.text)
        assert words in response.text, response.text
        assert counts(db) == before

    # Unknown participants, and work not submitted yet.
    refused(f"{BASE}/999/approval", {}, 404, "no participant 999")
    refused(f"{BASE}/999/bonuses", bonus, 404, "no participant 999")
    refused(f"{BASE}/{working_id}/approval", {}, 409, "has not submitted")
    refused(f"{BASE}/{working_id}/bonuses", bonus, 409, "has not submitted")
    # Amounts that are not a positive number of cents, and bodies that are not requests.
    for amount in (-1, 0, "abc", "1.234", "NaN", True, 100.01, None):
        refused(f"{BASE}/{done}/bonuses", {**bonus, "amount": amount}, 422, "amount")
    refused(f"{BASE}/{done}/bonuses", {**bonus, "reason": ""}, 422, "reason")
    refused(f"{BASE}/{done}/bonuses", {**bonus, "unique_token": "no"}, 422, "unique_token")
    refused(f"{BASE}/{done}/approval", {"message": "x", "extra": 1}, 422, "extra")
    # A rejection needs its message.
    refused(f"{BASE}/{done}/rejection", {}, 422, "needs a message")
    # Without the admin token nothing happens.
    assert client.post(f"{BASE}/{done}/approval", json={}).status_code == 401
    assert client.post(f"/api/admin/participants/{done}/approval", json={}).status_code == 401
    assert counts(db) == (0, 0, 0, ["submitted"])

    # Approving again answers the same and does nothing more; rejecting an approved
    # assignment is refused.
    first = client.post(f"{BASE}/{done}/approval", json={}, headers=ADMIN)
    assert first.status_code == 200
    again = client.post(f"{BASE}/{done}/approval", json={}, headers=ADMIN)
    assert again.status_code == 200 and again.json()["review"] == first.json()["review"]
    refused(f"{BASE}/{done}/rejection", {"message": "late"}, 409, "already approved")
    # A token used once is not reused for another bonus.
    assert client.post(f"{BASE}/{done}/bonuses", json=bonus, headers=ADMIN).status_code == 200
    refused(f"{BASE}/{done}/bonuses", {**bonus, "amount": "3.00"}, 409, "another bonus")
    assert counts(db) == (1, 1, 1, ["approved"])


def test_a_platform_refusal_stores_nothing(client: TestClient, db: Database) -> None:
    """The replica refuses what MTurk would (a decision on an assignment it already decided),
    and the study then records nothing."""
    done = submitted_worker(client, db, "WORKER1")
    with db.read() as s:
        assignment = s.scalars(select(ReplicaAssignment.assignment_id)).one()
    who = Reviewed(done, "mturk", "WORKER1", assignment, None)
    MTurkReplicaBackend(db).approve(who, "decided on the platform")
    response = client.post(f"{BASE}/{done}/rejection", json={"message": "no"}, headers=ADMIN)
    assert response.status_code == 409 and "is approved" in response.text
    assert counts(db)[:3] == (0, 0, 0)
    with pytest.raises(ReviewRefused, match="no assignment"):
        MTurkReplicaBackend(db).send_bonus("W", "NOSUCHASSIGNMENT", "1.00", "r", "tok-12345")


class FakeMTurk:
    """Records each call with its keyword arguments, as boto3's client receives them; fails
    as botocore's ClientError does when told to."""

    def __init__(self, error: str | None = None) -> None:
        self.calls: list[tuple[str, dict[str, Any]]] = []
        self.error = error

    def __getattr__(self, method: str) -> Any:
        def call(*args: Any, **kwargs: Any) -> dict[str, Any]:
            assert not args, "boto3's client takes keyword arguments only"
            self.calls.append((method, kwargs))
            if self.error is not None:
                failure = Exception(f"An error occurred ({self.error})")
                failure.response = {"Error": {"Code": self.error, "Message": "the reason"}}  # type: ignore[attr-defined]
                raise failure
            return {}

        return call


def test_the_boto3_adapter_sends_exactly_boto3s_keyword_arguments() -> None:
    fake = FakeMTurk()
    backend = MTurkClientBackend(fake)
    backend.approve(Reviewed(1, "mturk", "WORKER1", "ASSIGN1", None), "Thanks")
    backend.approve(Reviewed(2, "mturk", "WORKER2", "ASSIGN2", None), None)
    backend.reject(Reviewed(3, "mturk", "WORKER3", "ASSIGN3", None), "Not done", None)
    backend.pay_bonus(
        Reviewed(1, "mturk", "WORKER1", "ASSIGN1", None),
        "1.50",
        "Good teaching",
        "token-123",
        None,
    )
    assert fake.calls == [
        ("approve_assignment", {"AssignmentId": "ASSIGN1", "RequesterFeedback": "Thanks"}),
        ("approve_assignment", {"AssignmentId": "ASSIGN2"}),
        ("reject_assignment", {"AssignmentId": "ASSIGN3", "RequesterFeedback": "Not done"}),
        (
            "send_bonus",
            {
                "WorkerId": "WORKER1",
                "BonusAmount": "1.50",
                "AssignmentId": "ASSIGN1",
                "Reason": "Good teaching",
                "UniqueRequestToken": "token-123",
            },
        ),
    ]
    with pytest.raises(ReviewRefused, match="MTurk refused approve_assignment: the reason"):
        MTurkClientBackend(FakeMTurk("RequestError")).approve(
            Reviewed(1, "mturk", "W", "A", None), None
        )
    with pytest.raises(ReviewUnavailable, match="send_bonus failed"):
        MTurkClientBackend(FakeMTurk("ServiceFault")).pay_bonus(
            Reviewed(1, "mturk", "W", "A", None), "1.00", "r", "t", None
        )


def test_boto3_is_imported_only_when_chosen(monkeypatch: pytest.MonkeyPatch) -> None:
    made: list[tuple[Any, ...]] = []
    fake_boto3 = types.ModuleType("boto3")
    fake_boto3.client = lambda *args, **kwargs: made.append((args, kwargs)) or FakeMTurk()  # type: ignore[attr-defined]
    settings = Settings(database_url="sqlite:///x.db", review_backend="mturk")
    db: Any = object()
    monkeypatch.setitem(sys.modules, "boto3", None)  # not installed
    with pytest.raises(ApiError, match="needs the boto3 package"):
        make_backend(settings, db, "mturk")
    monkeypatch.setitem(sys.modules, "boto3", fake_boto3)
    assert isinstance(make_backend(settings, db, "mturk"), MTurkClientBackend)
    assert made == [
        (
            ("mturk",),
            {
                "region_name": "us-east-1",
                "endpoint_url": "https://mturk-requester-sandbox.us-east-1.amazonaws.com",
            },
        )
    ]
    replica = Settings(database_url="sqlite:///x.db")
    assert isinstance(make_backend(replica, db, "mturk"), MTurkReplicaBackend)
    assert len(made) == 1


def test_the_dashboard_reviews_through_the_mturk_backend(client: TestClient, db: Database) -> None:
    """With MTurk's client plugged in, the dashboard's routes call it and record what it took;
    what MTurk refuses is not recorded."""
    done = submitted_worker(client, db, "WORKER1")
    with db.read() as s:
        assignment = s.scalars(select(ReplicaAssignment.assignment_id)).one()
    state = client.app.state.server  # type: ignore[attr-defined]
    state.reviews["mturk"] = MTurkClientBackend(FakeMTurk("RequestError"))
    refused = client.post(f"{BASE}/{done}/approval", json={}, headers=ADMIN)
    assert refused.status_code == 409 and "MTurk refused" in refused.text
    assert counts(db)[:3] == (0, 0, 0)
    fake = FakeMTurk()
    state.reviews["mturk"] = MTurkClientBackend(fake)
    assert client.post(f"{BASE}/{done}/approval", json={}, headers=ADMIN).status_code == 200
    bonus = {"amount": 5, "reason": "Well taught", "unique_token": "token-mturk-1"}
    paid = client.post(f"{BASE}/{done}/bonuses", json=bonus, headers=ADMIN)
    assert paid.status_code == 200 and paid.json()["bonuses"][0]["backend"] == "mturk"
    assert client.post(f"{BASE}/{done}/bonuses", json=bonus, headers=ADMIN).status_code == 200
    assert fake.calls == [
        ("approve_assignment", {"AssignmentId": assignment}),
        (
            "send_bonus",
            {
                "WorkerId": "WORKER1",
                "BonusAmount": "5.00",
                "AssignmentId": assignment,
                "Reason": "Well taught",
                "UniqueRequestToken": "token-mturk-1",
            },
        ),
    ]
    # The replica was not touched.
    assert counts(db) == (1, 1, 0, ["submitted"])
