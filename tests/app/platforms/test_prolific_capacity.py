"""The server's capacity held on Prolific: the study's max_concurrent_submissions follows the
participants the server admits at once, the study is paused by the server while its queue
makes agents wait and started again once it drained (never a pause the researcher made), each
change logged and listed for the dashboard."""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient

from server.app.main import create_app
from server.app.platforms.prolific import ProlificClient
from server.app.platforms.prolific_capacity import (
    MAX_CONCURRENT,
    PAUSE_WAIT_SECONDS,
    Load,
    changes_for,
    follow,
    steady,
)
from server.app.platforms.prolific_replica import ReplicaTransport
from server.app.routers.prolific import follow_capacity
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import ProlificStudy, ProlificStudyChange
from server.app.updates.queue import QueueState
from tests.app.platforms.test_prolific import ADMIN, draft
from tests.support.server import ADMIN_TOKEN, study_config

CALM = Load(limit=2, awaited=0, oldest_wait_seconds=0.0, waiting=0)
BUSY = Load(limit=2, awaited=3, oldest_wait_seconds=PAUSE_WAIT_SECONDS, waiting=0)


def kinds(changes: list[Any]) -> list[tuple[str, int | None]]:
    return [(c.change, c.value) for c in changes]


def test_the_rule_follows_the_limit_pauses_under_load_and_starts_only_its_own_pause() -> None:
    assert kinds(changes_for("ACTIVE", 5, CALM, False)) == [(MAX_CONCURRENT, 2)]
    assert kinds(changes_for("ACTIVE", None, CALM, False)) == [(MAX_CONCURRENT, 2)]
    assert changes_for("ACTIVE", 2, CALM, False) == []
    unknown = Load(limit=None, awaited=0, oldest_wait_seconds=0.0, waiting=0)
    assert changes_for("ACTIVE", 5, unknown, False) == []  # no capacity yet: left alone
    assert kinds(changes_for("ACTIVE", 2, BUSY, False)) == [("PAUSE", None)]
    short = Load(limit=2, awaited=3, oldest_wait_seconds=PAUSE_WAIT_SECONDS - 0.5, waiting=0)
    assert changes_for("ACTIVE", 2, short, False) == []  # a short wait is not a queue
    line = Load(limit=2, awaited=0, oldest_wait_seconds=0.0, waiting=1)
    assert changes_for("ACTIVE", 2, line, False) == []  # the concurrency ends the line
    assert changes_for("PAUSED", 2, line, True) == []  # not drained while people wait
    assert kinds(changes_for("PAUSED", 2, CALM, True)) == [("START", None)]
    assert changes_for("PAUSED", 2, CALM, False) == []  # the researcher's pause stays
    assert changes_for("PAUSED", 2, BUSY, True) == []  # not drained yet
    for status in ("UNPUBLISHED", "SCHEDULED", "AWAITING REVIEW", "COMPLETED"):
        assert changes_for(status, 5, BUSY, True) == []
    # A wait pauses only when two readings in a row show it.
    assert steady(CALM, BUSY) == CALM and not steady(None, BUSY).overloaded
    assert steady(BUSY, BUSY).overloaded


def replica_client(db: Database) -> ProlificClient:
    return ProlificClient(
        "http://replica/prolific/api/v1",
        ADMIN_TOKEN,
        transport=ReplicaTransport(db, ADMIN_TOKEN),
        first_wait=0.0,
    )


def logged(db: Database) -> list[tuple[str, int | None, str]]:
    with db.read() as s:
        return [
            (c.change, c.value, c.outcome)
            for c in s.query(ProlificStudyChange).order_by(ProlificStudyChange.id)
        ]


def test_following_changes_the_study_on_prolific_and_logs_each_change(db: Database) -> None:
    client = replica_client(db)
    fields = {**draft(), "submissions_config": {"max_concurrent_submissions": 5}}
    study_id = client.create_study(fields)["id"]
    client.transition_study(study_id, "PUBLISH")

    assert kinds(follow(db, client, study_id, CALM)) == [(MAX_CONCURRENT, 2)]
    assert client.get_study(study_id)["submissions_config"]["max_concurrent_submissions"] == 2
    assert follow(db, client, study_id, CALM) == []  # in line: nothing sent
    assert kinds(follow(db, client, study_id, BUSY)) == [("PAUSE", None)]
    assert client.get_study(study_id)["status"] == "PAUSED"
    assert follow(db, client, study_id, BUSY) == []  # paused while it waits
    assert kinds(follow(db, client, study_id, CALM)) == [("START", None)]
    assert client.get_study(study_id)["status"] == "ACTIVE"
    # The researcher pauses: the server does not start it again.
    client.transition_study(study_id, "PAUSE")
    assert follow(db, client, study_id, CALM) == []
    assert logged(db) == [
        (MAX_CONCURRENT, 2, "done"),
        ("PAUSE", None, "done"),
        ("START", None, "done"),
    ]


class RefusesPatch(httpx.BaseTransport):
    def __init__(self, inner: httpx.BaseTransport) -> None:
        self.inner = inner

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        if request.method == "PATCH":
            return httpx.Response(400, json={"error": {"detail": "Cannot change this study."}})
        return self.inner.handle_request(request)


def test_a_change_prolific_refuses_is_logged_with_its_refusal(db: Database) -> None:
    client = replica_client(db)
    study_id = client.create_study(draft())["id"]
    client.transition_study(study_id, "PUBLISH")
    refusing = ProlificClient(
        "http://replica/prolific/api/v1",
        ADMIN_TOKEN,
        transport=RefusesPatch(ReplicaTransport(db, ADMIN_TOKEN)),
    )
    assert follow(db, refusing, study_id, CALM) == []
    [(change, value, outcome)] = logged(db)
    assert (change, value) == (MAX_CONCURRENT, 2)
    assert "Cannot change this study" in outcome


@pytest.fixture
def server(db: Database, settings: Settings, executor: ProcessPoolExecutor) -> Iterator[TestClient]:
    study = study_config(max_active_participants=3)
    with TestClient(create_app(settings, study, db=db, executor=executor)) as client:
        yield client


def test_the_server_holds_its_active_studies_to_its_load_and_the_dashboard_lists_it(
    server: TestClient, db: Database
) -> None:
    client = replica_client(db)
    study_id = client.create_study(draft())["id"]
    client.transition_study(study_id, "PUBLISH")
    state = server.app.state.server  # type: ignore[attr-defined]
    calm = QueueState(0, 0, 0, 0.0, 1, 0, 0)
    follow_capacity(state, calm)
    assert logged(db) == []  # no event said the study is active: not followed
    with db.write() as s:
        s.add(ProlificStudy(study_id=study_id, status="ACTIVE"))  # as its status event keeps it
    reading = follow_capacity(state, calm)
    assert client.get_study(study_id)["submissions_config"]["max_concurrent_submissions"] == 3
    busy = QueueState(2, 2, 2, 10.0, 1, 0, 0)
    reading = follow_capacity(state, busy, reading)
    assert client.get_study(study_id)["status"] == "ACTIVE"  # one reading of the wait: not yet
    follow_capacity(state, busy, reading)
    assert client.get_study(study_id)["status"] == "PAUSED"
    [view] = server.get("/api/admin/prolific-studies", headers=ADMIN).json()
    assert [(c["change"], c["value"], c["outcome"]) for c in view["changes"]] == [
        ("PAUSE", None, "done"),
        (MAX_CONCURRENT, 3, "done"),
    ]
    assert "2 participant(s) waiting for their agent's update" in view["changes"][0]["reason"]
