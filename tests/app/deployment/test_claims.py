"""Several servers on one database: an update is claimed by one server at a time, taken over
when the claiming server's lease expires, and stored only by the claim that holds it; the
other servers hear of it (PostgreSQL's notices); a stopped server gives its claims back."""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Iterator
from datetime import timedelta
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import update

from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import LearnerUpdate, utcnow
from server.app.study_file import StudyConfig
from server.app.updates.notices import Listener, channel_of
from server.app.updates.queue import UpdateQueue
from server.app.updates.store import Job, Stored, UpdateStore
from server.app.updates.worker import run_update
from tests.app.updates.test_updates import demonstrate, updates_of
from tests.support.server import (
    BOUND,
    gated_app,
    run_apart,
    study_config,
    teaching_participant,
    wait_until,
)


@pytest.fixture
def one_study() -> StudyConfig:
    return study_config(
        domains=[{"name": "navigation", "environments": ["two-rooms"]}],
        learners=["bam"],
        tutorial={"enabled": False},
    )


@pytest.fixture
def pending(db: Database, settings: Settings, one_study: StudyConfig) -> int:
    """A session with updates 1 and 2 pending and no server running: its id."""
    app, gated = gated_app(db, settings, one_study)
    with TestClient(app) as client:
        participant, session_id = teaching_participant(client)
        wait_until(lambda: updates_of(db, session_id)[0].status == "done", "update 0 done")
        gated.gate.clear()  # held: the server stops before they run
        for task in range(2):
            demonstrate(participant, session_id, task)
    gated.shutdown()
    assert [row.status for row in updates_of(db, session_id)] == ["done", "pending", "pending"]
    return session_id


def store(db: Database, study: StudyConfig, name: str) -> UpdateStore:
    return UpdateStore(db, study.settings_of, name, lease_seconds=30)


def expire_leases(db: Database) -> None:
    with db.write() as s:
        s.execute(update(LearnerUpdate).values(lease_until=utcnow() - timedelta(seconds=1)))


def test_an_update_is_stored_once_by_the_claim_that_holds_it(
    db: Database, one_study: StudyConfig, pending: int
) -> None:
    a, b = store(db, one_study, "server-a"), store(db, one_study, "server-b")
    # The stopped server had claimed update 1 (its run held) and gave the claim back.
    before = updates_of(db, pending)[1].runs
    job = a.load(pending)
    assert job is not None and (job.update_index, job.run) == (1, before + 1)
    # A's claim holds the update: B leaves it, and leaves the session's later update too (it
    # needs update 1's learner).
    assert b.load(pending) is None
    # A stalls past its lease (or died): B takes the update over.
    expire_leases(db)
    taken = b.load(pending)
    assert taken is not None and (taken.update_index, taken.run) == (1, before + 2)
    row = updates_of(db, pending)[1]
    assert (row.claimed_by, row.taken_from, row.runs) == ("server-b", "server-a", before + 2)
    outcome = run_update(taken.payload)
    # A comes back with its result: not stored, the update is B's.
    assert a.commit(job, outcome) == Stored(stored=False, more=False)
    assert a.fail(job, "too late", retry=True) is False
    assert updates_of(db, pending)[1].status == "pending"
    assert b.commit(taken, outcome) == Stored(stored=True, more=True)
    row = updates_of(db, pending)[1]
    assert (row.status, row.claimed_by, row.runs) == ("done", "server-b", before + 2)
    assert row.learner_state == outcome["learner_state"]
    # The next update, claimed by B before A: it runs once.
    following = b.load(pending)
    assert following is not None and (following.update_index, following.run) == (2, 1)
    assert a.load(pending) is None


def test_servers_claiming_at_once_get_the_update_once(
    db: Database, one_study: StudyConfig, pending: int
) -> None:
    before = updates_of(db, pending)[1].runs
    stores = [store(db, one_study, f"server-{n}") for n in range(6)]
    start = threading.Barrier(len(stores))
    jobs: list[Job | None] = [None] * len(stores)

    def claim(index: int) -> None:
        start.wait(BOUND)
        jobs[index] = stores[index].load(pending)

    threads = [threading.Thread(target=claim, args=(n,)) for n in range(len(stores))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(BOUND)
    claimed = [job for job in jobs if job is not None]
    assert len(claimed) == 1 and claimed[0].update_index == 1
    assert updates_of(db, pending)[1].runs == before + 1


def test_a_stopping_server_gives_its_claims_back(
    db: Database, one_study: StudyConfig, pending: int
) -> None:
    a, b = store(db, one_study, "server-a"), store(db, one_study, "server-b")
    before = updates_of(db, pending)[1].runs
    job = a.load(pending)
    assert job is not None
    a.release_all()  # A stops: B takes the update at once, with no lease to wait out
    taken = b.load(pending)
    assert taken is not None and taken.update_index == 1
    row = updates_of(db, pending)[1]
    assert (row.claimed_by, row.taken_from) == ("server-b", None)
    # A claim that did not run (the cluster was unreachable) is not counted as a run.
    b.release(taken)
    # A's claim counts (its update may have begun), B's does not.
    assert updates_of(db, pending)[1].runs == before + 1


@pytest.fixture
def loop() -> Iterator[asyncio.AbstractEventLoop]:
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    yield loop
    loop.call_soon_threadsafe(loop.stop)
    thread.join(BOUND)
    loop.close()


@pytest.mark.parametrize("backend", ["postgresql"])
def test_the_other_servers_hear_of_an_update_stored(
    db: Database, one_study: StudyConfig, pending: int, loop: asyncio.AbstractEventLoop
) -> None:
    heard: list[dict[str, Any]] = []
    channel = channel_of(db.engine)
    a = UpdateStore(db, one_study.settings_of, "server-a", channel=channel)
    listeners = [Listener(db.engine, channel, name, heard.append) for name in ("server-a", "b")]
    for listener in listeners:
        listener.start(loop)
    try:
        wait_until(lambda: all(n.listening.is_set() for n in listeners), "listening", BOUND)
        job = a.load(pending)
        assert job is not None
        a.await_update(pending, 2, since=1_000_000.0)
        assert a.commit(job, run_update(job.payload)).stored
        wait_until(lambda: len(heard) == 2, "the notices heard", BOUND)
    finally:
        for listener in listeners:
            listener.stop()
    # Heard by the other server only (not by the one that sent them), in order.
    assert heard == [
        {"awaited": pending, "update": 2, "since": 1_000_000.0, "from": "server-a"},
        {"processed": pending, "update": 1, "from": "server-a"},
    ]
    # The wait is in the database for every server's queue, until its update is done.
    (session,) = a.pending_sessions()
    assert (session.session_id, session.awaited_update) == (pending, 2)
    assert session.awaited_since == 1_000_000.0


def test_a_lease_is_renewed_while_its_server_lives(
    db: Database, one_study: StudyConfig, pending: int
) -> None:
    a, b = store(db, one_study, "server-a"), store(db, one_study, "server-b")
    assert a.load(pending) is not None
    expire_leases(db)
    assert a.renew() == 1  # A's heartbeat: its lease holds again
    assert b.load(pending) is None
    assert [s.session_id for s in b.pending_sessions()] == []  # nothing free to take


def test_a_wait_on_another_server_puts_its_session_first_here() -> None:
    """The order is the deployment's: a wait that began on another server earlier than this
    one's goes first here too; a wait that began here is told to the others, one told by them
    is not told back."""
    shared: list[tuple[int, int]] = []

    async def scenario() -> list[int]:
        queue = UpdateQueue(lambda session_id: 0, lambda s, t, since: shared.append((s, t)))
        queue.start()
        queue.enqueue_many([1, 2, 3])  # queued first, nobody waiting
        queue.mark_awaited(2, 1)  # a participant here waits for session 2's agent
        # Session 3's participant, on another server, began waiting a minute ago.
        queue.mark_awaited(3, 1, since_epoch=time.time() - 60)
        return [await queue.take() for _ in range(3)]

    assert run_apart(scenario) == [3, 2, 1]
    assert shared == [(2, 1)]
