"""The local MTurk replica holds one assignment of its HIT per worker, as MTurk does."""

from __future__ import annotations

from fastapi.testclient import TestClient
from sqlalchemy import select

from server.app.storage.db import Database
from server.app.storage.replica_models import ReplicaAssignment
from tests.server.conftest import ADMIN_TOKEN

ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}


def accept(client: TestClient, worker: str) -> tuple[int, str]:
    response = client.post(
        "/mturk/accept", data={"workerId": worker}, headers=ADMIN, follow_redirects=False
    )
    return response.status_code, response.headers.get("location", response.text)


def test_a_worker_holds_one_assignment_of_the_hit(client: TestClient, db: Database) -> None:
    status, first = accept(client, "W1")
    assert status == 303 and first.startswith("/mturk/work/")
    # Accepting again leads back to the assignment the worker holds: no second one.
    assert accept(client, "W1") == (303, first)
    status, other = accept(client, "W2")
    assert status == 303 and other != first
    with db.read() as s:
        rows = s.scalars(select(ReplicaAssignment).order_by(ReplicaAssignment.id)).all()
        assert [(r.worker_id, r.status) for r in rows] == [("W1", "accepted"), ("W2", "accepted")]
        assert rows[0].assignment_id != rows[1].assignment_id
        assignment = rows[0].assignment_id
    # Once submitted, the worker cannot take the HIT again.
    submitted = client.post(
        "/mturk/externalSubmit",
        data={"assignmentId": assignment, "completionCode": "X"},
        headers=ADMIN,
    )
    assert submitted.status_code == 200, submitted.text
    status, page = accept(client, "W1")
    assert status == 400 and "has already submitted assignment" in page
    # A returned assignment frees the worker: they may accept again.
    returned = client.post(f"{other}/return", headers=ADMIN, follow_redirects=False)
    assert returned.status_code in (200, 303)
    status, again = accept(client, "W2")
    assert status == 303 and again != other
    with db.read() as s:
        assert len(s.scalars(select(ReplicaAssignment)).all()) == 3
