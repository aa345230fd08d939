"""Places in the study: at most ``max_active_participants`` (default: the measured capacity) in
it at once; arrivals beyond wait, first come first in, as soon as a place frees; the queue and
the capacity on the dashboard's API."""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from datetime import timedelta
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import update

from server.app.main import create_app
from server.app.participants.statuses import mark_abandoned
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import Participant as ParticipantRow
from server.app.storage.models import utcnow
from server.app.updates.capacity import (
    LIVE_MINIMUM,
    Capacity,
    LongestUpdate,
    describe,
    measure_updates,
    participants_at_once,
)
from tests.support.server import (
    ADMIN_TOKEN,
    Participant,
    arrive,
    study_config,
    wait_for_updates,
)

ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}


@pytest.fixture
def full_client(
    db: Database, settings: Settings, executor: ProcessPoolExecutor
) -> Iterator[TestClient]:
    """A study with room for two participants at once."""
    app = create_app(settings, study_config(max_active_participants=2), db=db, executor=executor)
    with TestClient(app) as client:
        yield client


def arrival(client: TestClient, worker: str) -> tuple[Participant, str]:
    response = arrive(client, worker, f"A-{worker}")
    assert response.status_code == 201, response.text
    data = response.json()
    return Participant(client, data["token"]), data["participant"]["status"]


def place(participant: Participant) -> dict[str, object]:
    response = participant.client.post("/api/participant/place", headers=participant.headers)
    assert response.status_code == 200, response.text
    return dict(response.json())


def test_arrivals_beyond_the_limit_wait_and_go_in_first_come_first_in(
    full_client: TestClient, db: Database
) -> None:
    first, first_status = arrival(full_client, "W1")
    second, second_status = arrival(full_client, "W2")
    third, third_status = arrival(full_client, "W3")
    fourth, fourth_status = arrival(full_client, "W4")
    assert [first_status, second_status, third_status, fourth_status] == [
        "arrived",
        "arrived",
        "waiting",
        "waiting",
    ]
    # A waiting participant cannot begin: the refusal says why, and nothing changes.
    refused = third.post("/api/participant/consent", agree=True)
    assert refused.status_code == 409
    assert "full" in refused.json()["detail"]
    assert place(third) == {
        "admitted": False,
        "ahead": 0,
        "active": 2,
        "limit": 2,
        "ask_seconds": 3,
    }
    assert place(fourth)["ahead"] == 1
    # Arriving again (a reload) keeps their place in line.
    again = arrive(full_client, "W4", "A-W4")
    assert again.status_code == 200 and again.json()["participant"]["status"] == "waiting"
    # The first participant declines: a place frees, and the first in line takes it.
    first.act("/api/participant/consent", agree=False)
    assert place(fourth)["admitted"] is False  # the third is before them
    assert place(third)["admitted"] is True
    assert place(fourth) == {
        "admitted": False,
        "ahead": 0,
        "active": 2,
        "limit": 2,
        "ask_seconds": 3,
    }
    third.act("/api/participant/consent", agree=True)
    resumed = arrive(full_client, "W3", "A-W3")
    assert resumed.json()["participant"]["status"] == "consented"
    # A participant in the study asking for a place is in already.
    assert place(second)["admitted"] is True
    # A new arrival goes behind those waiting, even when a place frees at that moment.
    second.act("/api/participant/consent", agree=False)
    _, fifth_status = arrival(full_client, "W5")
    assert fifth_status == "waiting"
    assert place(fourth)["admitted"] is True


def test_a_waiting_participant_is_not_abandoned_nor_assigned_a_domain(
    full_client: TestClient, db: Database, settings: Settings
) -> None:
    for worker in ("W1", "W2"):
        arrival(full_client, worker)
    waiting, status = arrival(full_client, "W3")
    assert status == "waiting"
    long_ago = utcnow() - timedelta(minutes=settings.abandon_minutes + 1)
    with db.write() as s:
        s.execute(update(ParticipantRow).values(last_seen_at=long_ago))
    assert mark_abandoned(db, settings) == 2  # the two in the study, not the one waiting
    with db.read() as s:
        rows = {p.platform_participant_id: p for p in s.query(ParticipantRow)}
    assert rows["W3"].status == "waiting" and rows["W3"].domain is None
    # The abandoned ones hold no place any more: the waiting one goes in, and only then is
    # assigned a domain, at consent.
    assert place(waiting)["admitted"] is True
    waiting.act("/api/participant/consent", agree=True)
    with db.read() as s:
        row = s.query(ParticipantRow).filter_by(platform_participant_id="W3").one()
    assert row.status == "consented" and row.domain is not None


def test_a_waiting_page_that_stopped_asking_leaves_the_line(
    full_client: TestClient, db: Database
) -> None:
    for worker in ("W1", "W2"):
        arrival(full_client, worker)
    arrival(full_client, "W3")  # whose page is closed below
    still, _ = arrival(full_client, "W4")
    assert place(still)["ahead"] == 1
    with db.write() as s:
        s.execute(
            update(ParticipantRow)
            .where(ParticipantRow.platform_participant_id == "W3")
            .values(last_seen_at=utcnow() - timedelta(minutes=5))
        )
    assert place(still)["ahead"] == 0


def test_without_a_limit_in_the_study_file_the_measured_capacity_is_the_limit(
    db: Database, settings: Settings, executor: ProcessPoolExecutor
) -> None:
    every_second = settings.model_copy(update={"update_interval_seconds": 1.0})
    app = create_app(every_second, study_config(), db=db, executor=executor)
    with TestClient(app) as client:
        manager = app.state.server.updates
        # Not measured yet: no limit.
        unmeasured = client.get("/api/admin/queue", headers=ADMIN).json()
        assert unmeasured["limit"] is None and unmeasured["longest_update_seconds"] is None
        _, status = arrival(client, "W1")
        assert status == "arrived"
        # An update measured at 20 s, a participant queueing one every second: one at a time.
        manager.reference_seconds = 20.0
        manager.reference_longest = LongestUpdate(31.25, "flip", "bam")
        manager.reference_server_seconds = 0.5
        _, status = arrival(client, "W2")
        assert status == "waiting"
        queue = client.get("/api/admin/queue", headers=ADMIN).json()
    assert queue["capacity"] == 1 and queue["limit"] == 1
    assert queue["limit_from"] == "capacity"
    assert queue["measured_on"] == "the study's learners at start"
    assert queue["participants_active"] == 1 and queue["participants_waiting"] == 1
    assert queue["update_seconds"] == 20.0
    assert queue["server_seconds_per_update"] == 0.5
    assert queue["longest_update_seconds"] == 31.25
    assert queue["longest_update_of"] == "bam in flip"


def test_the_queue_shows_updates_pending_and_the_oldest_wait(
    full_client: TestClient, db: Database
) -> None:
    manager = full_client.app.state.server.updates  # type: ignore[attr-defined]
    participant, _ = arrival(full_client, "W1")
    participant.act("/api/participant/consent", agree=True)
    session = participant.act("/api/participant/start")["participant"]["current_session_id"]
    wait_for_updates(db)  # its first update done and stored
    # ... and the manager done with it (an update that ends clears its session's mark).
    deadline = time.monotonic() + 60
    while manager.backlog:
        assert time.monotonic() < deadline, manager.queue()
        time.sleep(0.05)
    # As if the participant had been waiting 12.5 s for the agent after their fifth episode.
    manager.order._awaited[session] = (manager.order.loop.time() - 12.5, 5)
    queue = full_client.get("/api/admin/queue", headers=ADMIN).json()
    assert queue["sessions_awaited"] == 1 and queue["oldest_wait_seconds"] >= 12.5
    assert queue["participants_active"] == 1 and queue["limit"] == 2
    assert queue["limit_from"] == "study file"
    assert full_client.get("/api/admin/queue").status_code == 401


def test_the_capacity_follows_the_cost_of_an_update_and_the_slots() -> None:
    # 75% of two slots, a participant queueing an update every 10 s, 0.25 s each: 60.
    assert participants_at_once(0.25, 2, 10.0) == 60
    assert participants_at_once(0.5, 2, 10.0) == 30
    assert participants_at_once(0.25, 4, 10.0) == 120
    assert participants_at_once(60.0, 1, 10.0) == 1  # never none
    with pytest.raises(ValueError):
        participants_at_once(0.0, 2, 10.0)


def test_the_capacity_counts_the_servers_own_work_where_it_shares_the_cores() -> None:
    # Two update processes on two cores, which also do the server's 0.05 s per update: 75% of
    # 2 cores x 10 s / (0.25 + 0.05) s = 50, not the 60 of the updates alone.
    assert participants_at_once(0.25, 2, 10.0, server_seconds=0.05, cores=2) == 50
    # Two update processes on eight cores: the slots, not the cores, are the limit.
    assert participants_at_once(0.25, 2, 10.0, server_seconds=0.05, cores=8) == 60
    # The slots elsewhere (a cluster's workers): the server's work takes nothing from them.
    assert participants_at_once(0.25, 2, 10.0, server_seconds=0.05) == 60
    with pytest.raises(ValueError):
        participants_at_once(0.25, 2, 10.0, server_seconds=-0.01, cores=2)
    line = describe(Capacity(50, 0.25, 2, 10.0, "the study's learners at start", None, 0.05))
    assert "the server's own work 0.05 s of a core per update" in line
    assert "server's own work" not in describe(Capacity(60, 0.25, 2, 10.0, "the latest 30"))


def test_the_longest_reference_update_is_found_across_sessions_and_said(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The longest single update of every session timed (not the session with the highest
    mean), the warm-up replay not counted; ``serve``'s line says it beside the capacity."""
    from server.app.updates import capacity, worker

    durations = {"wall": [0.1, 0.2, 0.3], "flip": [0.5, 0.05, 0.05]}
    clock = [0.0]

    def run_update(job: dict[str, Any]) -> dict[str, Any]:
        index = job["base_state"] or 0
        clock[0] += durations[job["environment"]][index]
        return {"learner_state": index + 1}

    monkeypatch.setattr(worker, "run_update", run_update)
    monkeypatch.setattr(capacity.time, "perf_counter", lambda: clock[0])
    sessions = [
        {"environment": name, "learner": "bam", "episodes": [[], []]} for name in ("wall", "flip")
    ]
    cost = measure_updates({"jobs": sessions})
    assert cost.mean_seconds == pytest.approx(1.2 / 6)  # wall's mean is the higher: 0.2
    assert cost.longest == LongestUpdate(pytest.approx(0.5), "flip", "bam")

    line = describe(
        Capacity(60, cost.mean_seconds, 2, 10.0, "the study's learners at start", cost.longest)
    )
    assert line.startswith("Capacity: 60 participants teaching at once")
    assert "The longest update, bam in flip, takes 0.50 s" in line
    assert "longest" not in describe(Capacity(60, 0.2, 2, 10.0, "the latest 30 updates"))


def test_the_capacity_is_measured_on_the_latest_updates_once_there_are_enough() -> None:
    from server.app.updates.manager import UpdateManager
    from server.app.updates.policies import PolicyCache

    db: Database = None  # type: ignore[assignment]
    manager = UpdateManager(db, PolicyCache(), lambda name: {}, workers=1)
    assert manager.capacity() is None
    manager.reference_seconds = 1.0
    capacity = manager.capacity()
    assert capacity is not None and capacity.update_seconds == 1.0
    for _ in range(LIVE_MINIMUM - 1):
        manager._costs.append(0.125)
    capacity = manager.capacity()
    assert capacity is not None and capacity.update_seconds == 1.0
    manager._costs.append(0.125)
    capacity = manager.capacity()
    assert capacity is not None and capacity.update_seconds == 0.125
    assert capacity.measured_on == f"the latest {LIVE_MINIMUM} updates"
    assert capacity.participants == participants_at_once(0.125, 1, 10.0) == 60


def test_the_live_capacity_counts_the_servers_cpu_time_per_update(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Once enough updates ran, the server's own work is its process's CPU time from the end
    of the first of the latest updates to the end of the last, over the updates between."""
    from server.app.updates import manager as manager_module
    from server.app.updates.manager import UpdateManager
    from server.app.updates.policies import PolicyCache

    monkeypatch.setattr(manager_module, "available_cores", lambda: 1)
    db: Database = None  # type: ignore[assignment]
    manager = UpdateManager(db, PolicyCache(), lambda name: {}, workers=1)
    for index in range(LIVE_MINIMUM + 1):
        manager._costs.append(0.125)
        manager._cpu_marks.append(3.0 + 0.125 * index)  # 0.125 s of the server's CPU each
    capacity = manager.capacity()
    assert capacity is not None and capacity.server_seconds == pytest.approx(0.125)
    # 75% of one core x 10 s / (0.125 + 0.125) s: half of the 60 of the updates alone.
    assert capacity.participants == 30


@pytest.mark.parametrize("share_timed", [True, False])
def test_the_reference_updates_are_timed_a_session_at_a_time_and_averaged_per_update(
    share_timed: bool,
) -> None:
    """Each session is one job (a server stopped meanwhile waits for one session's updates,
    not for all of them), only the first warms the process up, and the capacity's update time
    is the mean over every update of every session. The server's own work is timed after
    them; where that fails, the capacity is stated without it."""
    from concurrent.futures import Executor, Future

    from server.app.updates.capacity import UpdateCost
    from server.app.updates.manager import UpdateManager
    from server.app.updates.policies import PolicyCache
    from server.app.updates.queue import ProcessGate
    from tests.support.server import run_apart

    sessions = [
        {"episodes": [[]] * 3, "mean": 1.0, "longest": 3.0, "environment": "flip"},
        {"episodes": [[]] * 7, "mean": 2.0, "longest": 2.5, "environment": "wall"},
    ]
    asked: list[dict[str, Any]] = []

    class Timing(Executor):
        def submit(self, fn: Any, /, *args: Any, **kwargs: Any) -> Future[Any]:
            future: Future[Any] = Future()
            if fn is measure_updates:
                asked.append(args[0])
                session = args[0]["jobs"][0]
                longest = LongestUpdate(session["longest"], session["environment"], "bam")
                future.set_result(UpdateCost(session["mean"], longest))
            else:  # worker_ready: the one process is warm
                future.set_result(1)
            return future

    shares: list[float] = []

    def server_share(stop: threading.Event) -> float:
        # The capacity is not stated while the server's own work is being timed.
        assert manager.capacity() is None
        shares.append(0.5)
        if not share_timed:
            raise RuntimeError("the scratch study's server did not start")
        return 0.5

    manager: UpdateManager

    async def measure() -> tuple[float | None, LongestUpdate | None]:
        nonlocal manager
        db: Database = None  # type: ignore[assignment]
        manager = UpdateManager(
            db,
            PolicyCache(),
            lambda name: {},
            workers=1,
            executor=Timing(),
            reference_jobs=sessions,
            server_share=server_share,
        )
        manager.order.start()
        manager._slots = asyncio.Semaphore(2)
        manager._processes = ProcessGate(1, manager.order.priority)
        manager.runner.start(manager._spawn)
        await asyncio.wait_for(manager._measure_reference(), 60)
        return manager.reference_seconds, manager.reference_longest

    # In a thread of its own: the browser tests may leave a loop running.
    seconds, longest = run_apart(measure)
    assert [request["jobs"] for request in asked] == [[sessions[0]], [sessions[1]]]
    assert [request["warm"] for request in asked] == [True, False]
    assert seconds == pytest.approx((4 * 1.0 + 8 * 2.0) / 12)
    # The longest update of all the sessions, not of the last or of the slowest on average.
    assert longest == LongestUpdate(3.0, "flip", "bam")
    # The server's own work is timed once, after the updates, and counted.
    assert shares == [0.5]
    capacity = manager.capacity()
    assert capacity is not None
    assert capacity.server_seconds == (0.5 if share_timed else None)
    assert capacity.measured_on == "the study's learners at start"
