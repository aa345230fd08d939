"""Learner updates off the request path: one evaluation per update, in order, an agent step
waiting only for its own learner, pending updates surviving a restart, failures recorded."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select, update

from server import learners
from server.app.main import create_app
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import Event, LearnerUpdate, LearningSession
from server.app.updates.worker import PARENT_CHECK_SECONDS
from server.domains import make
from server.domains.base import ACTIONS
from server.learners.records import DemonstrationStep
from server.teacher import Teacher
from tests.support.server import (
    BOUND,
    Participant,
    gated_app,
    study_config,
    teaching_participant,
    wait_for_updates,
    wait_until,
)

# One environment, one BAM agent with its reference settings (where a test needs an update to
# last, it holds it: ``gated_app``).
SLOW_STUDY = {
    "domains": [{"name": "navigation", "environments": ["two-rooms"]}],
    "learners": ["bam"],
    "learner_settings": {"bam": {}},
    "tutorial": {"enabled": False},
}


def demonstrate(
    participant: Participant, session_id: int, task: int, seed: int = 0
) -> dict[str, Any]:
    """A full demonstration by the simulated teacher from a random start of ``task``."""
    base = participant.session(session_id)
    view = participant.get(base)
    env = make(view["summary"]["environment"])
    teacher = Teacher(env, seed=seed)
    if view["teaching"]["task"] != task:
        participant.act(f"{base}/task", task=task)
    state = participant.act(f"{base}/reset")["session"]["agent"]["state"]
    while env.is_goal(task, state):
        state = participant.act(f"{base}/reset")["session"]["agent"]["state"]
    participant.act(f"{base}/mode", mode="demonstrate")
    for _ in range(env.horizon):
        data = participant.act(f"{base}/move", action=ACTIONS[teacher.next_action(task, state)])
        state = data["session"]["agent"]["state"]
        if data["outcome"]["episode_ended"]:
            return data
    return participant.act(f"{base}/end-episode")


def updates_of(db: Database, session_id: int) -> list[LearnerUpdate]:
    with db.read() as s:
        return list(
            s.scalars(
                select(LearnerUpdate)
                .where(LearnerUpdate.session_id == session_id)
                .order_by(LearnerUpdate.update_index)
            )
        )


def test_one_evaluation_per_update_in_order(client: TestClient, db: Database) -> None:
    participant, tutorial = teaching_participant(client)
    demonstrate_all = participant.get(participant.session(tutorial))
    tasks = len(demonstrate_all["environment"]["tasks"])
    for round_ in range(2):
        for task in range(tasks):
            demonstrate(participant, tutorial, task, seed=round_)
    wait_for_updates(db)
    rows = updates_of(db, tutorial)
    assert [row.update_index for row in rows] == list(range(2 * tasks + 1))
    assert all(row.status == "done" for row in rows)
    assert [row.episodes for row in rows] == list(range(2 * tasks + 1))
    assert all(a.actions < b.actions for a, b in pairwise(rows))
    assert all(0.0 <= row.normalized_return <= 1.0 + 1e-9 for row in rows)
    assert all(a.finished_at <= b.finished_at for a, b in pairwise(rows))
    assert rows[0].objective is None and rows[-1].objective is not None
    # The last learner state holds exactly what the events say the learner observed.
    env = make(demonstrate_all["summary"]["environment"])
    learner = learners.restore(env, learners.loads(rows[-1].learner_state))
    assert learner.updates == 2 * tasks
    with db.read() as s:
        events = s.scalars(select(Event).where(Event.session_id == tutorial)).all()
    demonstrated = sum(e.record == "demonstration" for e in events) + sum(
        e.stay_state is not None for e in events
    )
    assert len(learner.data.demonstrations) == demonstrated
    assert len(learner.data.idle_moves) == sum(e.record == "transition" for e in events)
    policy = np.frombuffer(rows[-1].greedy_policy, dtype=np.int8).reshape(tasks, env.num_states)
    assert policy.min() >= 0 and policy.max() < len(ACTIONS)


def test_an_agent_step_waits_for_its_own_update_only(db: Database, settings: Settings) -> None:
    app, gated = gated_app(db, settings, study_config(**SLOW_STUDY))
    with TestClient(app) as client:
        participant, session_id = teaching_participant(client)
        other, other_session = teaching_participant(TestClient(client.app), "W2", "A2")
        wait_for_updates(db)
        gated.gate.clear()  # from now on no update runs until the gate opens
        base = participant.session(session_id)
        ended = demonstrate(participant, session_id, 0)
        assert ended["session"]["learning"]["pending"] == 1
        participant.act(f"{base}/reset")  # away from the goal the demonstration ended on
        participant.act(f"{base}/mode", mode="agent")
        updates = app.state.server.updates
        with ThreadPoolExecutor(1) as pool:
            waiting = pool.submit(participant.act, f"{base}/agent-step")
            wait_until(lambda: updates.queue().sessions_awaited == 1, "the agent step waits")
            # While the agent waits for its update, the other participant's moves go on.
            other_base = other.session(other_session)
            for name in ["UP", "DOWN", "LEFT", "RIGHT"] * 3:
                other.act(f"{other_base}/move", action=name)
            assert not waiting.done()
            assert updates.queue().sessions_awaited == 1
            gated.gate.set()
            step = waiting.result(BOUND)
    gated.shutdown()
    rows = updates_of(db, session_id)
    assert rows[1].status == "done"
    assert step["outcome"]["learning_wait_seconds"] > 0
    assert step["session"]["learning"] == {"pending": 0, "updates": 1}
    env = make("two-rooms")
    policy = np.frombuffer(rows[1].greedy_policy, dtype=np.int8).reshape(
        len(env.tasks), env.num_states
    )
    assert ACTIONS.index(step["outcome"]["action"]) == policy[0, step["outcome"]["state"]]


def test_pending_updates_survive_a_restart(
    db: Database, settings: Settings, executor: ProcessPoolExecutor
) -> None:
    study = study_config(**SLOW_STUDY)
    app, gated = gated_app(db, settings, study)
    with TestClient(app) as client:
        participant, session_id = teaching_participant(client)
        wait_for_updates(db)
        gated.gate.clear()  # the three episodes' updates are held: the server stops first
        for task in range(3):
            demonstrate(participant, session_id, task)
        token, seq = participant.token, participant.seq
    gated.shutdown()  # the held update runs now, for nobody: its server has stopped
    rows = updates_of(db, session_id)
    assert [row.status for row in rows] == ["done", "pending", "pending", "pending"]
    with TestClient(create_app(settings, study, db=db, executor=executor)) as client:
        wait_for_updates(db)
        participant = Participant(client, token, seq)
        participant.act(f"{participant.session(session_id)}/reset")
        participant.act(f"{participant.session(session_id)}/mode", mode="agent")
        participant.act(f"{participant.session(session_id)}/agent-step")
    rows = updates_of(db, session_id)
    assert [row.update_index for row in rows] == [0, 1, 2, 3]
    assert all(row.status == "done" for row in rows)
    assert all(a.finished_at <= b.finished_at for a, b in pairwise(rows))


def test_a_failed_update_is_recorded_and_the_session_goes_on(
    client: TestClient, db: Database
) -> None:
    participant, session_id = teaching_participant(client)
    wait_for_updates(db)
    # Corrupt data: feedback on an agent step that never happened makes the learner refuse.
    with db.write() as s:
        s.add(
            Event(
                participant_id=1,
                session_id=session_id,
                seq=10_000,
                kind="feedback",
                record="feedback",
                feedback=1,
                request_hash="x",
                response="{}",
            )
        )
    demonstrate(participant, session_id, 0)
    wait_for_updates(db)
    rows = updates_of(db, session_id)
    assert rows[1].status == "failed" and "feedback" in rows[1].error
    assert participant.get(participant.session(session_id))["teaching"]["learning"]["pending"] == 0
    with db.write() as s:
        s.execute(update(Event).where(Event.seq == 10_000).values(record=None))
    demonstrate(participant, session_id, 1)
    wait_for_updates(db)
    rows = updates_of(db, session_id)
    assert rows[2].status == "done"
    participant.act(f"{participant.session(session_id)}/reset")
    participant.act(f"{participant.session(session_id)}/mode", mode="agent")
    assert (
        participant.act(f"{participant.session(session_id)}/agent-step")["session"]["learning"][
            "updates"
        ]
        == 2
    )


def test_a_learner_is_rebuilt_from_the_events_when_no_state_is_saved(
    client: TestClient, db: Database
) -> None:
    participant, session_id = teaching_participant(client)
    demonstrate(participant, session_id, 0)
    demonstrate(participant, session_id, 1)
    wait_for_updates(db)
    with db.write() as s:
        s.execute(update(LearnerUpdate).values(learner_state=None))
    demonstrate(participant, session_id, 0, seed=3)
    wait_for_updates(db)
    rows = updates_of(db, session_id)
    assert rows[3].status == "done"
    env = make(participant.get(participant.session(session_id))["summary"]["environment"])
    learner = learners.restore(env, learners.loads(rows[3].learner_state))
    with db.read() as s:
        events = s.scalars(select(Event).where(Event.session_id == session_id)).all()
    assert len(learner.data.demonstrations) == sum(
        e.record == "demonstration" for e in events
    ) + sum(e.stay_state is not None for e in events)


def test_the_learning_state_can_be_awaited(db: Database, settings: Settings) -> None:
    app, gated = gated_app(db, settings, study_config(**SLOW_STUDY))
    with TestClient(app) as client:
        participant, session_id = teaching_participant(client)
        wait_for_updates(db)
        gated.gate.clear()
        demonstrate(participant, session_id, 0)
        learning = f"{participant.session(session_id)}/learning"
        assert participant.get(learning) == {"pending": 1, "updates": 0}
        with ThreadPoolExecutor(1) as pool:
            awaited = pool.submit(participant.get, f"{learning}?wait=30")
            # Nobody is counted as waiting (the agent's turn is not next): the request's wait
            # is seen among the queue's waiters.
            order = app.state.server.updates.order
            wait_until(lambda: session_id in order._waiters, "the request waits")
            assert not awaited.done()
            gated.gate.set()
            assert awaited.result(BOUND) == {"pending": 0, "updates": 1}
        with db.read() as s:
            session = s.get(LearningSession, session_id)
            assert session is not None and session.policy_update == 1
        response = client.get(f"{learning}?wait=99", headers=participant.headers)
        assert response.status_code == 422
        assert "wait" in response.text
    gated.shutdown()


# A server process that makes its update pool, starts its workers, then dies without shutting
# the pool down (as SIGKILL, or a SIGTERM that reached the workers first and made it start new
# ones on its way out, leave them).
_DYING_SERVER = """
import os, time
from server.app.updates.pool import new_executor

if __name__ == "__main__":
    pool = new_executor(2, 0)
    for job in [pool.submit(time.sleep, 0.5) for _ in range(2)]:
        job.result()
    print(" ".join(str(pid) for pid in pool._processes), flush=True)
    os._exit(0)
"""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f"/proc/{pid}/stat") as stat:  # a zombie is gone for our purpose
        return stat.read().split(")")[-1].split()[0] != "Z"


@pytest.mark.skipif(not Path("/proc").exists(), reason="reads /proc (Linux)")
def test_update_workers_leave_when_their_server_dies(tmp_path: Path) -> None:
    script = tmp_path / "dying_server.py"
    script.write_text(_DYING_SERVER)
    result = subprocess.run(
        [sys.executable, str(script)],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        timeout=60,  # stdout stays open until the workers, which inherit it, are gone
    )
    assert result.returncode == 0, result.stderr
    workers = [int(pid) for pid in result.stdout.split()]
    assert len(workers) == 2 and all(pid != os.getpid() for pid in workers)
    deadline = time.monotonic() + 10 * PARENT_CHECK_SECONDS
    while any(_alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(pid) for pid in workers), "update workers outlived their server"


@pytest.mark.parametrize(
    ("threads", "running", "share"),
    [(2, 1, 2), (2, 2, 1), (2, 3, 1), (4, 2, 2), (4, 3, 1), (1, 1, 1)],
)
def test_updates_side_by_side_share_the_planner_threads(
    threads: int, running: int, share: int
) -> None:
    from server.cores import share_threads

    assert share_threads(threads, running) == share


def test_an_update_gives_its_planner_the_threads_its_job_names(tmp_path: Path) -> None:
    """The server names each update's planner threads in its job; the update process's
    planner uses them, and the update's result does not depend on them."""
    from server.app.updates.worker import run_update
    from server.learners import planning

    env = make("doorway")
    teacher = Teacher(env, seed=3)
    records = [
        DemonstrationStep(task, *step)
        for task in range(len(env.tasks))
        for step in teacher.demonstration(task, env.sample_start(task, np.random.default_rng(task)))
    ]
    job = {
        "environment": "doorway",
        "learner": "bam",
        "seed": 1,
        "settings": {"alternations": 2},
        "base_state": None,
        "records": records,
        "fit": True,
    }
    results = []
    with planning.using_planner_threads(planning.planner_threads()):  # put back after
        for threads in (3, 1):
            outcome = run_update({**job, "threads": threads})
            assert planning.planner_threads() == threads
            results.append(outcome)
    for key in ("learner_state", "greedy_policy", "objective", "normalized_return"):
        assert results[0][key] == results[1][key]


def test_an_update_reports_its_own_cpu_time(executor: ProcessPoolExecutor) -> None:
    """The CPU time an update's process spent on it (what the capacity counts where the update
    processes share the server's cores): some, and no more than the update's own wall time
    on one thread (not the process's since it started)."""
    from server.app.updates.worker import run_update

    env = make("wall")
    teacher = Teacher(env, seed=0)
    records = [
        DemonstrationStep(0, *step)
        for step in teacher.demonstration(0, env.sample_start(0, np.random.default_rng(0)))
    ]
    job = {
        "environment": "wall",
        "learner": "bam",
        "seed": 0,
        "settings": {},
        "base_state": None,
        "records": records,
        "fit": True,
        "threads": 1,
    }
    # In an update process (nothing else runs in it): the first loads what it has not loaded.
    executor.submit(run_update, job).result()
    started = time.perf_counter()
    outcome = executor.submit(run_update, job).result()
    wall = time.perf_counter() - started
    assert 0 < outcome["cpu_seconds"] <= wall


_LATE_WORKER = """
import os, sys, time
from server.app.updates.worker import worker_init

worker_init(0, int(sys.argv[1]))
print("stayed", flush=True)
time.sleep(30)
"""


@pytest.mark.parametrize("server", ["gone", "parent"])
def test_an_update_worker_whose_server_died_before_it_started_leaves(
    tmp_path: Path, server: str
) -> None:
    """A worker spawned to replace killed ones just before its server died starts with init as
    its parent: it must leave at once, not wait for a parent change that never comes. One
    started by its live server stays (and leaves when it dies, above)."""
    script = tmp_path / "late_worker.py"
    script.write_text(_LATE_WORKER)
    server_pid = 0 if server == "gone" else os.getpid()  # 0: no process is anyone's parent
    worker = subprocess.Popen(
        [sys.executable, str(script), str(server_pid)], stdout=subprocess.PIPE, text=True
    )
    try:
        if server == "gone":
            assert worker.wait(timeout=30) == 0
            assert worker.stdout is not None and worker.stdout.read() == ""
        else:
            assert worker.stdout is not None and worker.stdout.readline() == "stayed\n"
            assert worker.poll() is None
    finally:
        worker.kill()
        worker.wait()


def test_a_waiter_wakes_on_its_own_update_at_once_and_polls_for_other_processes(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """An update this process commits wakes the waiter at once, however long the database poll
    interval; one that another process committed (no notification here) is found by the
    poll; and a wait with neither ends False at its timeout."""
    import asyncio

    from server.app.updates import queue as queue_module

    class FakeDb:
        processed = -1

    async def scenario() -> tuple[bool, float, bool, float, bool, float]:
        loop = asyncio.get_running_loop()
        queue = queue_module.UpdateQueue(lambda session_id: FakeDb.processed)
        queue.start()
        monkeypatch.setattr(queue_module, "DB_POLL_SECONDS", 60.0)
        started = loop.time()
        loop.call_later(0.2, queue.notify, 7, 1)
        woken = await queue.wait(7, 1, timeout=10.0)
        notified_after = loop.time() - started

        monkeypatch.setattr(queue_module, "DB_POLL_SECONDS", 0.2)
        started = loop.time()
        loop.call_later(0.3, setattr, FakeDb, "processed", 2)
        found = await queue.wait(8, 2, timeout=10.0)
        polled_after = loop.time() - started

        started = loop.time()
        timed_out = await queue.wait(9, 5, timeout=0.5)
        waited = loop.time() - started
        return woken, notified_after, found, polled_after, timed_out, waited

    # In a thread of its own: after the browser tests, this thread may run an event loop.
    with ThreadPoolExecutor(1) as pool:
        outcome = pool.submit(asyncio.run, scenario()).result()
    woken, notified_after, found, polled_after, timed_out, waited = outcome
    assert woken and notified_after < 1.0  # not the 60 s poll interval
    assert found and 0.3 <= polled_after < 2.0  # the commit at 0.3 s, polls every 0.2 s
    assert not timed_out and 0.4 < waited < 2.0


def loaded_kernels() -> tuple[int, int]:
    """In an update process: its pid and how many of the planner's kernels it holds compiled
    (loaded from numba's cache or compiled)."""
    from server.learners import _kernels

    kernels = (
        _kernels.soft_forward_tasks,
        _kernels.soft_forward_chunks,
        _kernels.soft_backward_tasks,
        _kernels.soft_backward_chunks,
    )
    return os.getpid(), sum(1 for kernel in kernels if kernel.signatures)


@pytest.mark.slow
def test_update_processes_start_with_the_server_and_load_their_kernels_first(
    tmp_path: Path,
) -> None:
    """The update processes start when the server does, not on the first participant's
    update, and load the planner's kernels before they take any update (server.learners.
    warmup; tests/learners/test_warmup.py checks that it loads all an update uses)."""
    import asyncio

    from server.app.updates.manager import UpdateManager
    from server.app.updates.policies import PolicyCache
    from tests.support.databases import migrated_sqlite

    database = Database.from_url(migrated_sqlite(tmp_path / "study.db"))

    async def scenario() -> tuple[int, list[tuple[int, int]]]:
        manager = UpdateManager(database, PolicyCache(), lambda name: {}, workers=2, niceness=0)
        await manager.start()
        try:
            executor = getattr(manager.runner, "executor", None)
            assert executor is not None
            started = len(executor._processes)
            probes = [await asyncio.wrap_future(executor.submit(loaded_kernels)) for _ in range(3)]
        finally:
            await manager.stop()
        return started, probes

    try:
        # In a thread of its own: after the browser tests, this thread may run an event loop.
        with ThreadPoolExecutor(1) as pool:
            started, probes = pool.submit(asyncio.run, scenario()).result()
    finally:
        database.dispose()
    assert started == 2  # both processes, before any update
    assert all(count == 4 for _, count in probes), probes  # no update had run in them
