"""The order of learner updates: what someone waits for goes first, a demonstration never waits
for an update, and the agent shown after episode k is the agent recorded after episode k."""

from __future__ import annotations

import asyncio
import threading
import time
from concurrent.futures import Executor, Future
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import LearnerUpdate, LearningSession
from server.app.updates.queue import ProcessGate, UpdateQueue
from server.domains import make
from server.domains.base import ACTIONS
from tests.app.updates.test_updates import demonstrate
from tests.support.server import (
    BOUND,
    Gated,
    gated_app,
    run_apart,
    study_config,
    teaching_participant,
    wait_for_updates,
)


class Scripted:
    """The update queue with one slot whose updates are held until released, recording the
    order in which sessions were dispatched. Session ``s`` has ``pending[s]`` updates."""

    def __init__(self, pending: dict[int, int]) -> None:
        self.queue = UpdateQueue(lambda session_id: self.processed[session_id])
        self.queue.start()
        self.pending = pending
        self.processed = dict.fromkeys(pending, 0)
        self.order: list[int] = []
        self.release = asyncio.Event()
        self.started = asyncio.Event()

    async def dispatch(self) -> None:
        """One slot: the next session's update runs once the one before ended."""
        while True:
            session_id = await self.queue.take()
            more = False
            try:
                if self.processed[session_id] < self.pending[session_id]:
                    self.order.append(session_id)
                    self.started.set()
                    await self.release.wait()
                    self.release.clear()
                    self.processed[session_id] += 1
                    more = self.processed[session_id] < self.pending[session_id]
                self.queue.notify(session_id, self.processed[session_id])
            finally:
                self.queue.finish(session_id, more)

    async def next_started(self) -> None:
        await asyncio.wait_for(self.started.wait(), BOUND)
        self.started.clear()

    async def step(self) -> None:
        """Let the running update finish, and wait until the next one starts."""
        self.release.set()
        await self.next_started()


def test_an_update_someone_waits_for_goes_before_one_nobody_waits_for() -> None:
    async def scenario() -> tuple[list[int], dict[int, tuple[float, int]], list[bool]]:
        script = Scripted({1: 1, 2: 2, 3: 1, 4: 1, 5: 1})
        queue = script.queue
        dispatcher = asyncio.ensure_future(script.dispatch())
        queue.enqueue_many([1])  # runs at once: the one slot is free
        await script.next_started()
        queue.enqueue_many([2, 3])  # queued in this order, nobody waiting
        # Session 4's agent step waits, gives up (503) and its participant retries later:
        # the wait was for nothing meanwhile, but the session stays awaited.
        gave_up = await queue.wait(4, 1, timeout=0.05)
        queue.mark_awaited(3, 1)  # session 3's participant lets its agent try, after 4's wait
        queue.enqueue_many([5])
        await script.step()  # 1 done: 4 (awaited first), not 2 (queued first)
        await script.step()  # 4 done: 3 (awaited second)
        marks = queue.awaited()
        await script.step()  # 3 done: nobody waits; 2 then 5 in the order they were queued
        await script.step()  # 2's first update done: 5 was queued before 2 came back
        await script.step()
        waited = [await queue.wait(s, 1, timeout=BOUND) for s in (1, 3, 4, 5)]
        script.release.set()
        await asyncio.sleep(0)
        dispatcher.cancel()
        await asyncio.gather(dispatcher, return_exceptions=True)
        return script.order, marks, [gave_up, *waited]

    order, marks, waits = run_apart(scenario)
    assert order == [1, 4, 3, 2, 5, 2]
    # While 3 was being updated it was still awaited, and 4, done, was not any more.
    assert list(marks) == [3]
    assert waits == [False, True, True, True, True]


def test_a_freed_process_goes_to_the_prepared_update_awaited_longest() -> None:
    """Updates read from the database wait for a process: the one someone waits for goes
    first, also when the waiting began after it was read (its priority is read when a process
    frees); the others go in the order they came; a cancelled waiter neither takes a process
    nor loses one."""

    async def scenario() -> tuple[list[int], int]:
        queue = UpdateQueue(lambda session_id: 0)
        queue.start()
        gate = ProcessGate(1, queue.priority)
        got: list[int] = []

        async def prepared(session_id: int) -> None:
            await gate.acquire(session_id)
            got.append(session_id)

        await gate.acquire(0)  # the one process is busy
        waiters = {s: asyncio.ensure_future(prepared(s)) for s in (1, 2, 3, 4, 5)}
        while gate.waiting < 5:
            await asyncio.sleep(0)
        queue.mark_awaited(3, 1)  # its participant lets the agent try: 3 was read third
        queue.mark_awaited(5, 1)
        waiters[2].cancel()  # its server request went away, say
        await asyncio.gather(waiters[2], return_exceptions=True)
        for _ in range(4):
            before = len(got)
            gate.release()
            while len(got) == before:
                await asyncio.sleep(0)
        await asyncio.gather(*(w for s, w in waiters.items() if s != 2))
        return got, gate.free

    got, free = run_apart(scenario)
    assert got == [3, 5, 1, 4]  # awaited longest first, then the order they came in
    assert free == 0  # the last holder (4) still has the one process


def test_a_process_gate_that_shrinks_hands_out_no_process_until_enough_are_back() -> None:
    async def scenario() -> list[int]:
        gate = ProcessGate(2, lambda session_id: (1, 0.0))
        got: list[int] = []

        async def prepared(session_id: int) -> None:
            await gate.acquire(session_id)
            got.append(session_id)

        await gate.acquire(0)
        await gate.acquire(1)
        gate.resize(-1)  # a cluster worker left: one process fewer
        waiter = asyncio.ensure_future(prepared(2))
        gate.release()  # 0 done: still one held, one process left: none free
        await asyncio.sleep(0.05)
        handed_early = list(got)
        gate.release()  # 1 done: the one process is free
        await asyncio.wait_for(waiter, BOUND)
        return [*handed_early, -1, *got]

    assert run_apart(scenario) == [-1, 2]


def test_a_session_awaited_for_a_later_update_stays_first_until_that_one_is_done() -> None:
    async def scenario() -> list[int]:
        script = Scripted({1: 1, 2: 3, 3: 1})
        queue = script.queue
        dispatcher = asyncio.ensure_future(script.dispatch())
        queue.enqueue_many([1])
        await script.next_started()
        queue.enqueue_many([3])
        queue.mark_awaited(2, 3)  # the agent after episode 3 is awaited: three updates
        for _ in range(4):
            await script.step()
        script.release.set()
        await asyncio.sleep(0)
        dispatcher.cancel()
        await asyncio.gather(dispatcher, return_exceptions=True)
        return script.order

    # 2's updates one after the other, in its episodes' order, before 3 (nobody waits for it).
    assert run_apart(scenario) == [1, 2, 2, 2, 3]


ONE_AGENT = {
    "domains": [{"name": "navigation", "environments": ["wall"]}],
    "learners": ["bam"],
    "tutorial": {"enabled": False},
    "agents_per_environment": 1,
}


def one_slot_app(db: Database, settings: Settings) -> tuple[Any, Gated]:
    return gated_app(db, settings, study_config(**ONE_AGENT))


def sessions_by_seed(db: Database, *session_ids: int) -> dict[int, int]:
    """Session ids by their learner seed (what ``Gated.started`` records)."""
    with db.read() as s:
        return {s.get(LearningSession, i).seed: i for i in session_ids}  # type: ignore[union-attr]


def test_demonstrations_go_on_while_updates_wait_and_each_agent_is_the_one_recorded(
    db: Database, settings: Settings
) -> None:
    app, gated = one_slot_app(db, settings)
    with TestClient(app) as client:
        teacher, taught = teaching_participant(client)
        trier, tried = teaching_participant(TestClient(app), "W2", "A2")
        demonstrate(teacher, taught, 0)  # its update loads the kernels in this process
        wait_for_updates(db)
        gated.gate.clear()  # from now on no update runs until the gate opens
        gated.started.clear()
        # The first participant demonstrates three episodes in a row: none waits for an update.
        # (The first of their updates takes the one slot at once, and waits there.)
        for episode in range(3):
            ended = demonstrate(teacher, taught, (episode + 1) % 2, seed=episode)
            assert ended["session"]["learning"]["pending"] == episode + 1
        # The second demonstrates once (after the first's three) and lets the agent try.
        demonstrate(trier, tried, 0)
        base = trier.session(tried)
        trier.act(f"{base}/reset")
        assert trier.act(f"{base}/mode", mode="agent")["session"]["learning"]["pending"] == 1
        seeds = sessions_by_seed(db, taught, tried)
        gated.gate.set()
        step = trier.act(f"{base}/agent-step")
        wait_for_updates(db)
        teacher_base = teacher.session(taught)
        teacher.act(f"{teacher_base}/reset")
        teacher.act(f"{teacher_base}/mode", mode="agent")
        teacher_step = teacher.act(f"{teacher_base}/agent-step")
    started = [seeds[seed] for seed in gated.started]
    # After the update already running, the one the trier waited for went first, before the
    # two queued before it.
    assert started[:3] == [taught, tried, taught]
    # Then the teacher's last one, and the trier's next if its agent's step (from a random
    # start) reached the goal and ended the episode: each update ran once.
    queued_by_step = step["outcome"].get("update_queued")
    assert queued_by_step in (None, 2)
    assert sorted(started[3:]) == sorted([taught] + ([tried] if queued_by_step else []))
    # Each agent step is the greedy action of the learner recorded after the latest episode.
    for session_id, response, index in ((tried, step, 1), (taught, teacher_step, 4)):
        latest = (queued_by_step or index) if session_id == tried else index
        with db.read() as s:
            row = s.scalar(
                select(LearnerUpdate).where(
                    LearnerUpdate.session_id == session_id, LearnerUpdate.update_index == index
                )
            )
            assert row is not None and row.status == "done"
            session = s.get(LearningSession, session_id)
            assert session is not None and session.policy_update == latest
        env = make("wall")
        policy = np.frombuffer(row.greedy_policy, dtype=np.int8).reshape(
            len(env.tasks), env.num_states
        )
        outcome = response["outcome"]
        task = response["session"]["task"]
        assert outcome["action"] == ACTIONS[policy[task, outcome["state"]]]


def test_a_slots_next_update_is_read_from_the_database_while_its_last_one_runs(
    db: Database, settings: Settings
) -> None:
    """The process does not wait for the database: with one slot, the next session's update
    is read while the one before is running (held here), and runs only after it."""
    app, gated = one_slot_app(db, settings)
    with TestClient(app) as client:
        teacher, taught = teaching_participant(client)
        other, theirs = teaching_participant(TestClient(app), "W2", "A2")
        demonstrate(teacher, taught, 0)
        wait_for_updates(db)
        manager = app.state.server.updates
        loaded: list[int] = []
        load = manager.store.load

        def reading(session_id: int) -> Any:
            job = load(session_id)
            loaded.append(session_id)
            return job

        manager.store.load = reading
        gated.gate.clear()
        gated.started.clear()
        demonstrate(teacher, taught, 1)  # its update takes the one slot and is held there
        deadline = time.monotonic() + BOUND
        while taught not in loaded and time.monotonic() < deadline:
            time.sleep(0.05)
        demonstrate(other, theirs, 0)
        while theirs not in loaded and time.monotonic() < deadline:
            time.sleep(0.05)
        assert loaded == [taught, theirs]
        assert gated.started == []  # the first is still held: the second was read meanwhile
        seeds = sessions_by_seed(db, taught, theirs)
        gated.gate.set()
        wait_for_updates(db)
    assert [seeds[seed] for seed in gated.started] == [taught, theirs]


class HeldPool(Executor):
    """An update pool whose jobs end when the test says (``end``, from any thread)."""

    def __init__(self) -> None:
        self.jobs: list[tuple[int, Future[Any]]] = []  # (session, its future), as submitted
        self.threads: list[int] = []  # the planner threads each job was given
        self.submitted = threading.Condition()

    def submit(self, fn: Any, /, *args: Any, **kwargs: Any) -> Future[Any]:
        future: Future[Any] = Future()
        with self.submitted:
            self.jobs.append((args[0]["session"], future))
            self.threads.append(args[0]["threads"])
            self.submitted.notify_all()
        return future

    def wait_for(self, count: int) -> bool:
        with self.submitted:
            return self.submitted.wait_for(lambda: len(self.jobs) >= count, BOUND)


def test_a_freed_update_process_takes_the_next_prepared_update_while_the_event_loop_is_busy() -> (
    None
):
    """With many participants the server's event loop is busy for tens of milliseconds at a
    time; an update process that waited for a turn of it between updates sat idle. The next
    prepared update is handed the process in the thread that sees the last one end."""
    from server.app.updates.runners import LocalUpdates

    pool = HeldPool()
    runner = LocalUpdates(workers=1, niceness=0, threads=1, executor=pool)

    async def scenario() -> tuple[bool, list[tuple[dict[str, Any], int, float]]]:
        gate = ProcessGate(1, lambda session_id: (1, 0.0))
        first = asyncio.ensure_future(runner.run({"session": 1}, "a", gate, 1))
        second = asyncio.ensure_future(runner.run({"session": 2}, "b", gate, 2))
        while not (len(pool.jobs) == 1 and gate.waiting == 1):
            await asyncio.sleep(0)
        # The loop is busy (this coroutine does not yield) while the first update ends.
        threading.Thread(target=pool.jobs[0][1].set_result, args=({"done": 1},)).start()
        started_meanwhile = pool.wait_for(2)
        pool.jobs[1][1].set_result({"done": 2})
        return started_meanwhile, list(await asyncio.gather(first, second))

    started_meanwhile, outcomes = run_apart(scenario)
    assert started_meanwhile, "the second update waited for the event loop to start"
    assert [session for session, _ in pool.jobs] == [1, 2]
    assert [(outcome, deaths) for outcome, deaths, _ in outcomes] == [
        ({"done": 1}, 0),
        ({"done": 2}, 0),
    ]
    assert all(seconds >= 0 for _, _, seconds in outcomes)


@pytest.mark.parametrize(
    ("queued", "threads"),
    [(0, [2, 1]), (1, [1, 1])],
    ids=["nothing-queued", "a-session-queued"],
)
def test_an_update_has_the_spare_cores_only_while_no_other_update_waits(
    monkeypatch: pytest.MonkeyPatch, queued: int, threads: list[int]
) -> None:
    """Two update processes on two cores, two planner threads: an update that starts alone
    takes both, unless another update waits for a slot (it would take the other core within
    moments, and the first one's spare thread would spin against it); the next update, with
    the first still running, takes its share, one."""
    from server.app.updates import runners

    monkeypatch.setattr(runners, "available_cores", lambda: 2)
    pool = HeldPool()
    runner = runners.LocalUpdates(
        workers=2, niceness=0, threads=2, executor=pool, queued=lambda: queued
    )

    async def scenario() -> None:
        gate = ProcessGate(2, lambda session_id: (1, 0.0))
        first = asyncio.ensure_future(runner.run({"session": 1}, "a", gate, 1))
        while len(pool.jobs) < 1:
            await asyncio.sleep(0)
        second = asyncio.ensure_future(runner.run({"session": 2}, "b", gate, 2))
        while len(pool.jobs) < 2:
            await asyncio.sleep(0)
        for _, future in pool.jobs:
            future.set_result({"done": True})
        await asyncio.gather(first, second)

    run_apart(scenario)
    assert pool.threads == threads


def test_an_update_handed_a_process_while_another_waits_for_one_takes_its_share(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Two prepared updates wait for the gate's processes; when one frees, the update it goes
    to plans on one thread, not both: the other prepared update takes the next process."""
    from server.app.updates import runners

    monkeypatch.setattr(runners, "available_cores", lambda: 2)
    pool = HeldPool()
    runner = runners.LocalUpdates(workers=2, niceness=0, threads=2, executor=pool)

    async def scenario() -> None:
        gate = ProcessGate(0, lambda session_id: (1, float(session_id)))
        runs = [asyncio.ensure_future(runner.run({"session": s}, str(s), gate, s)) for s in (1, 2)]
        while gate.waiting < 2:
            await asyncio.sleep(0)
        gate.resize(1)  # one process frees: session 1's update takes it, session 2's waits
        while len(pool.jobs) < 1:
            await asyncio.sleep(0)
        pool.jobs[0][1].set_result({"done": True})  # its process goes to session 2's
        while len(pool.jobs) < 2:
            await asyncio.sleep(0)
        pool.jobs[1][1].set_result({"done": True})
        await asyncio.gather(*runs)

    run_apart(scenario)
    assert [session for session, _ in pool.jobs] == [1, 2]
    assert pool.threads == [1, 2]


def test_an_update_whose_process_died_reports_it_and_the_pool_is_replaced(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The dead pool's update raises ``WorkerDied``; the next update runs on a new pool, and
    the process it held is handed on."""
    from concurrent.futures.process import BrokenProcessPool

    from server.app.updates import runners
    from server.app.updates.pool import WorkerDied

    broken, fresh = HeldPool(), HeldPool()
    monkeypatch.setattr(runners, "new_executor", lambda workers, niceness: fresh)
    runner = runners.LocalUpdates(workers=1, niceness=0, threads=1, executor=broken)
    runner._own_executor = True  # as a pool the runner made itself
    monkeypatch.setattr(runner, "_start_workers", lambda: None)

    async def scenario() -> tuple[BaseException | None, dict[str, Any]]:
        gate = ProcessGate(1, lambda session_id: (1, 0.0))
        first = asyncio.ensure_future(runner.run({"session": 1}, "a", gate, 1))
        while not broken.jobs:
            await asyncio.sleep(0)
        broken.jobs[0][1].set_exception(BrokenProcessPool("a process died"))
        died = (await asyncio.gather(first, return_exceptions=True))[0]
        second = asyncio.ensure_future(runner.run({"session": 2}, "b", gate, 2))
        while not fresh.jobs:
            await asyncio.sleep(0)
        fresh.jobs[0][1].set_result({"done": 2})
        outcome, _, _ = await second
        return died if isinstance(died, BaseException) else None, outcome

    died, outcome = run_apart(scenario)
    assert isinstance(died, WorkerDied)
    assert runner.executor is fresh
    assert outcome == {"done": 2}


def test_the_update_processes_count_the_sessions_queued_for_a_slot() -> None:
    """The manager's local processes read how many sessions wait for a slot from its queue
    (the planner threads an update gets depend on it)."""
    from server.app.updates.manager import UpdateManager
    from server.app.updates.policies import PolicyCache
    from server.app.updates.runners import LocalUpdates

    db: Database = None  # type: ignore[assignment]
    manager = UpdateManager(db, PolicyCache(), lambda name: {}, workers=2)
    runner = manager.runner
    assert isinstance(runner, LocalUpdates)

    async def scenario() -> tuple[int, int]:
        manager.order.start()
        before = runner.queued()
        manager.order.enqueue_many([4, 7, 4])
        return before, runner.queued()

    assert run_apart(scenario) == (0, 2)


def test_the_update_processes_count_a_session_being_read_from_the_database_as_waiting() -> None:
    """A session taken for a slot is read from the database before it claims a process; an
    update that starts meanwhile would otherwise count no other waiting, take the spare cores,
    and have the read update take the other core from it within moments. While the read is
    under way the session counts as waiting, and not once it is read."""
    from server.app.updates.manager import UpdateManager
    from server.app.updates.policies import PolicyCache
    from server.app.updates.runners import LocalUpdates

    db: Database = None  # type: ignore[assignment]
    manager = UpdateManager(db, PolicyCache(), lambda name: {}, workers=2)
    runner = manager.runner
    assert isinstance(runner, LocalUpdates)
    reading, release = threading.Event(), threading.Event()

    def load(session_id: int) -> None:
        reading.set()
        release.wait(BOUND)
        return None  # nothing pending after all: the session's turn ends here

    manager.store.load = load  # type: ignore[method-assign]

    async def scenario() -> tuple[int, int, int]:
        manager.order.start()
        manager._slots = asyncio.Semaphore(4)
        await manager._slots.acquire()  # as the dispatcher does before it takes a session
        manager.order.enqueue_many([9])
        session_id = await manager.order.take()
        before = runner.queued()
        processing = asyncio.ensure_future(manager._process(session_id))
        assert await asyncio.to_thread(reading.wait, BOUND)
        during = runner.queued()
        release.set()
        await processing
        return before, during, runner.queued()

    assert run_apart(scenario) == (0, 1, 0)
