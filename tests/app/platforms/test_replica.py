"""The local MTurk replica holds one assignment of its HIT per worker, as MTurk does, also for
workers who accept at once on a server of several threads."""

from __future__ import annotations

import html
import re
import threading
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from urllib.parse import parse_qs, urlsplit

import httpx
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from server.app.main import create_app
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import Participant
from server.app.storage.replica_models import ReplicaAssignment, ReplicaHit
from server.app.study_file import StudyConfig
from tests.support.server import ADMIN_TOKEN, BOUND, live

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


def test_the_holder_of_a_reused_assignment_keeps_it(client: TestClient, db: Database) -> None:
    """W1 returns the HIT and its assignment goes to W2; W1's old study URL gets a page that
    says so, W2 goes on, and the replica and the server agree on who holds the assignment."""

    def study_url(work: str) -> str:
        page = client.get(work, headers=ADMIN)
        assert page.status_code == 200, page.text
        url = re.search(r'src="(/study\?[^"]+)"', page.text)
        assert url is not None, page.text
        return html.unescape(url.group(1))

    def server_statuses() -> dict[str, str]:
        with db.read() as s:
            rows = s.execute(select(Participant.platform_participant_id, Participant.status)).all()
        return {row.platform_participant_id: row.status for row in rows}

    def replica_statuses() -> list[tuple[str, str]]:
        with db.read() as s:
            rows = s.scalars(select(ReplicaAssignment).order_by(ReplicaAssignment.id)).all()
        return [(row.worker_id, row.status) for row in rows]

    _, first_work = accept(client, "W1")
    first_url = study_url(first_work)
    assert client.get(first_url).status_code == 200
    assert server_statuses() == {"W1": "arrived"}
    # W1 returns the HIT: the server knows at once.
    client.post(f"{first_work}/return", headers=ADMIN, follow_redirects=False)
    assert server_statuses() == {"W1": "returned"}
    # W2 accepts and gets the same assignment id.
    _, second_work = accept(client, "W2")
    second_url = study_url(second_work)
    assert (
        parse_qs(urlsplit(second_url).query)["assignmentId"]
        == (parse_qs(urlsplit(first_url).query)["assignmentId"])
    )
    second_browser = TestClient(client.app)
    assert second_browser.get(second_url).status_code == 200
    # W1 opens the old URL in a new browser: a page saying the task went to another worker.
    old = TestClient(client.app).get(first_url)
    assert old.status_code == 409 and "You returned this task" in old.text
    assert server_statuses() == {"W1": "returned", "W2": "arrived"}
    assert replica_statuses() == [("W1", "returned"), ("W2", "accepted")]
    # W2 returns it too and W1 accepts again: W1 gets it back and goes on where they were.
    client.post(f"{second_work}/return", headers=ADMIN, follow_redirects=False)
    _, third_work = accept(client, "W1")
    assert study_url(third_work) == first_url
    assert TestClient(client.app).get(first_url).status_code == 200
    assert server_statuses() == {"W1": "arrived", "W2": "returned"}
    assert replica_statuses() == [("W1", "returned"), ("W2", "returned"), ("W1", "accepted")]


@pytest.mark.parametrize("backend", ["postgresql"])
def test_workers_accepting_at_once_share_the_hit_and_hold_one_assignment_each(
    db: Database, settings: Settings, study: StudyConfig, executor: ProcessPoolExecutor
) -> None:
    """Six workers accept the HIT at once, each twice (a double click), over real HTTP: one
    HIT, one assignment per worker, no assignment id twice."""
    workers = [f"W{n}" for n in range(6)] * 2
    ready = threading.Barrier(len(workers))

    def accept_at_once(base: str, worker: str) -> httpx.Response:
        ready.wait(timeout=BOUND)
        return httpx.post(
            f"{base}/mturk/accept", data={"workerId": worker}, headers=ADMIN, timeout=BOUND
        )

    app = create_app(settings, study, db=db, executor=executor)
    with live(app) as base, ThreadPoolExecutor(len(workers)) as pool:
        answers = list(pool.map(lambda worker: accept_at_once(base, worker), workers))
    assert [answer.status_code for answer in answers] == [303] * len(workers)
    with db.read() as s:
        hits = s.scalars(select(ReplicaHit.hit_id)).all()
        rows = s.scalars(select(ReplicaAssignment)).all()
    assert len(hits) == 1
    assert sorted(row.worker_id for row in rows) == sorted(set(workers))
    assert len({row.assignment_id for row in rows}) == len(rows)
    assert {row.hit_id for row in rows} == set(hits)
