"""Learner updates, off the request path.

An episode end commits its events and a pending ``learner_updates`` row, then hands the session
to the ``UpdateManager``. The manager runs each session's pending updates in order, one at a time
per session, in a pool of processes (``BAM_UPDATE_WORKERS``, at a lower CPU priority than the
server so that moves stay fast; an update running alone splits its planner's tasks over
``BAM_UPDATE_THREADS`` threads, updates side by side share them): the worker restores the
learner from the latest saved state (or builds a new one), replays the events since, updates
it, stores its greedy policies and scores them (exact normalised return). The server then
commits the new learner state with the evaluation, and an agent step waiting for that
session's update goes on.

The order minimises what participants wait for. A session's updates are awaited from the moment
its agent's turn is next (the participant lets the agent try: ``expect``) or an agent step or the
page waits for them in agent mode (``wait``), until they are done, across the waiter's retries;
awaited sessions go first, the one awaited longest first (the longest wait is the one the
participant feels), and the others take turns in the order their updates were queued. Order
changes only between sessions: a session's updates run one at a time in episode order, each from
the learner state the one before saved, so the agent shown after episode k is the agent recorded
after episode k. No request but the agent step waits for an update: demonstrations, moves and
episode ends go on while the session's updates are pending.

Pending updates are found again in the database when the server starts, so none is lost by a
restart. With ``BAM_UPDATE_SCHEDULER`` the same function runs on the workers of a Dask cluster
instead of the local processes (``server.app.updates.cluster``), in the same order.
"""

from __future__ import annotations

import asyncio
import logging
import time
import traceback
from collections import deque
from concurrent.futures import Executor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from sqlalchemy import func, select

from server.app.storage.db import Database
from server.app.storage.models import Event, LearnerUpdate, LearningSession, utcnow
from server.app.updates.policies import PolicyCache, decode
from server.cores import available_cores, share_threads
from server.domains import make as make_environment

if TYPE_CHECKING:
    from server.app.updates.cluster import UpdateCluster


from server.app.updates.capacity import (
    LIVE_MINIMUM,
    LIVE_UPDATES,
    Capacity,
    describe,
    measure_update_cost,
    participants_at_once,
)
from server.app.updates.pool import UpdatesUnavailable, WorkerDied, new_executor
from server.app.updates.worker import records_of, run_update, worker_ready

log = logging.getLogger("bam_study.updates")

MAX_ATTEMPTS = 3  # a worker process dying this often on one update marks it failed
RESCAN_SECONDS = 30.0
# A waiting agent step is woken at once by an update this process commits; it looks in the
# database this often for one another process committed (a thread hop and a query each: at
# 200 participants, once a second per waiter was a measurable share of the server's CPU).
DB_POLL_SECONDS = 5.0
RETRY_SECONDS = 5.0  # a session whose update could not be run (database, scheduler) waits
CLUSTER_WATCH_SECONDS = 10.0  # how often a ready server asks its Dask cluster about the workers


@dataclass(frozen=True)
class QueueState:
    sessions_queued: int  # sessions with updates pending, waiting for a slot
    sessions_updating: int  # sessions with an update running
    sessions_awaited: int  # of those, sessions someone waits for
    oldest_wait_seconds: float  # how long the longest of those waits has lasted
    slots: int  # updates that run at once
    completed: int  # updates done since the server started
    failed: int


@dataclass
class Job:
    update_id: int
    session_id: int
    update_index: int
    environment: str
    payload: dict[str, Any]


class UpdateManager:
    """Runs the sessions' pending learner updates (see the module docstring)."""

    def __init__(
        self,
        db: Database,
        policies: PolicyCache,
        learner_settings: Any,
        workers: int = 2,
        niceness: int = 10,
        executor: Executor | None = None,
        threads: int = 1,
        cluster: UpdateCluster | None = None,
        update_interval_seconds: float = 10.0,
        reference_jobs: list[dict[str, Any]] | None = None,
    ) -> None:
        self.db = db
        self.policies = policies
        self.learner_settings = learner_settings  # learner name -> settings dict
        self.workers = workers
        self.niceness = niceness
        self.threads = threads
        self._executor = executor
        self._own_executor = executor is None
        self.cluster = cluster  # updates on a Dask cluster (server.app.updates.cluster), not a pool
        self._capacity = workers  # updates run at once: the slots
        self._loop: asyncio.AbstractEventLoop | None = None
        self._ready: dict[int, int] = {}  # session -> turn
        self._turn = 0
        self._running: set[int] = set()
        self._again: set[int] = set()
        # session -> (when someone began waiting, the update index they wait for)
        self._awaited: dict[int, tuple[float, int]] = {}
        self._processed: dict[int, int] = {}
        self._waiters: dict[int, list[asyncio.Future[None]]] = {}
        self._tasks: set[asyncio.Task[Any]] = set()
        self._wake: asyncio.Event | None = None
        self._slots: asyncio.Semaphore | None = None
        self._in_flight = 0  # updates submitted to the processes and not yet returned
        self.completed = 0
        self.failed = 0
        self.warm_processes = 0  # update processes known to have loaded the kernels
        self.ready = False  # every update process is warm
        self._stopping = False
        # The capacity (server.app.capacity): jobs timed once the processes are warm (none:
        # not measured at start), their mean wall time, and the wall times of the latest updates.
        self.update_interval_seconds = update_interval_seconds
        self.reference_jobs = reference_jobs
        self.reference_seconds: float | None = None
        self._costs: deque[float] = deque(maxlen=LIVE_UPDATES)

    # -- lifecycle ---------------------------------------------------------------------------
    async def start(self) -> None:
        self._stopping = False
        self._loop = asyncio.get_running_loop()
        self._wake = asyncio.Event()
        self._slots = asyncio.Semaphore(self._capacity)
        if self.cluster is not None:
            self._spawn(self._watch_cluster())
        else:
            if self._executor is None:
                self._executor = new_executor(self.workers, self.niceness)
                self._start_workers()
            self._spawn(self._await_warm())
        self._spawn(self._dispatch())
        self._spawn(self._rescan_forever())
        if self.reference_jobs:
            self._spawn(self._measure_reference())

    async def stop(self) -> None:
        self._stopping = True
        for task in list(self._tasks):
            task.cancel()
        for task in list(self._tasks):
            try:
                await task
            except (asyncio.CancelledError, Exception):
                pass
        for futures in self._waiters.values():
            for future in futures:
                future.cancel()
        if self._own_executor and self._executor is not None:
            executor, self._executor = self._executor, None
            # Updates not started stay pending in the database and run after the next start.
            # The processes are waited for (one in an update finishes it), and the pool's
            # queues released: a server stopped by a signal ends right after this, without
            # Python's exit handlers, and their semaphores would be reported leaked.
            await asyncio.to_thread(executor.shutdown, wait=True, cancel_futures=True)

    def _spawn(self, coroutine: Any) -> asyncio.Task[Any]:
        task = asyncio.ensure_future(coroutine)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    # -- queueing ----------------------------------------------------------------------------
    def submit(self, session_ids: list[int]) -> None:
        """Thread-safe: these sessions have new pending updates."""
        if not session_ids or self._loop is None:
            return
        self._loop.call_soon_threadsafe(self._enqueue_many, list(session_ids))

    def _enqueue_many(self, session_ids: list[int]) -> None:
        for session_id in session_ids:
            self._enqueue(session_id)

    def _enqueue(self, session_id: int) -> None:
        if session_id in self._running:
            self._again.add(session_id)
            return
        if session_id not in self._ready:
            self._turn += 1
            self._ready[session_id] = self._turn
        assert self._wake is not None
        self._wake.set()

    @property
    def backlog(self) -> int:
        """Sessions waiting for a worker or being updated."""
        return len(self._ready) + len(self._running)

    def expect(self, session_id: int, target: int) -> None:
        """Thread-safe: the session's agent's turn is next (the participant let it try) and its
        update ``target`` is pending: someone waits for it from now on."""
        if self._loop is None:
            return
        self._loop.call_soon_threadsafe(self._expect, session_id, target)

    def _expect(self, session_id: int, target: int) -> None:
        assert self._loop is not None
        if self._processed.get(session_id, -1) >= target:
            return
        since, awaited = self._awaited.get(session_id, (self._loop.time(), target))
        self._awaited[session_id] = (since, max(awaited, target))
        self._enqueue(session_id)

    async def wait(
        self, session_id: int, target: int, timeout: float, awaited: bool = True
    ) -> bool:
        """Wait until the session's update ``target`` is processed; False on timeout. With
        ``awaited`` (an agent step, or the page in agent mode) someone waits for it: the
        session goes first until it is done, also after this wait times out (the waiter
        retries). Callable from any event loop (the manager's state lives on its own)."""
        assert self._loop is not None
        if asyncio.get_running_loop() is not self._loop:
            waiting = asyncio.run_coroutine_threadsafe(
                self._wait(session_id, target, timeout, awaited), self._loop
            )
            return await asyncio.wrap_future(waiting)
        return await self._wait(session_id, target, timeout, awaited)

    async def _wait(self, session_id: int, target: int, timeout: float, awaited: bool) -> bool:
        assert self._loop is not None
        deadline = self._loop.time() + timeout
        if awaited:
            self._expect(session_id, target)
        else:
            self._enqueue(session_id)
        while True:
            if self._processed.get(session_id, -1) >= target:
                return True
            remaining = deadline - self._loop.time()
            if remaining <= 0:
                return False
            future: asyncio.Future[None] = self._loop.create_future()
            self._waiters.setdefault(session_id, []).append(future)
            try:
                await asyncio.wait_for(future, min(remaining, DB_POLL_SECONDS))
            except TimeoutError:
                # Also look in the database, in case another process did the update.
                processed = await asyncio.to_thread(self._processed_in_db, session_id)
                self._note_processed(session_id, processed)
            finally:
                waiters = self._waiters.get(session_id, [])
                if future in waiters:
                    waiters.remove(future)
                if not waiters:
                    self._waiters.pop(session_id, None)

    def _note_processed(self, session_id: int, index: int) -> None:
        self._processed[session_id] = max(self._processed.get(session_id, -1), index)
        awaited = self._awaited.get(session_id)
        if awaited is not None and awaited[1] <= self._processed[session_id]:
            del self._awaited[session_id]

    def _notify(self, session_id: int, index: int) -> None:
        self._note_processed(session_id, index)
        for future in self._waiters.get(session_id, []):
            if not future.done():
                future.set_result(None)

    def priority(self, session_id: int) -> tuple[int, float]:
        """The dispatch order (smallest first): awaited sessions by how long they have been
        awaited, then the others by when their updates were queued."""
        awaited = self._awaited.get(session_id)
        if awaited is not None:
            return (0, awaited[0])
        return (1, float(self._ready.get(session_id, 0)))

    def queue(self) -> QueueState:
        """What the dashboard shows of the live queue (call it on the manager's loop, or
        accept a snapshot a moment old)."""
        now = self._loop.time() if self._loop is not None else 0.0
        waits = [now - since for since, _ in list(self._awaited.values())]
        return QueueState(
            sessions_queued=len(self._ready),
            sessions_updating=len(self._running),
            sessions_awaited=len(waits),
            oldest_wait_seconds=max(waits, default=0.0),
            slots=self._capacity,
            completed=self.completed,
            failed=self.failed,
        )

    # -- dispatching -------------------------------------------------------------------------
    async def _dispatch(self) -> None:
        assert self._slots is not None and self._wake is not None
        while True:
            await self._slots.acquire()
            try:
                while not self._ready:
                    self._wake.clear()
                    await self._wake.wait()
            except BaseException:
                self._slots.release()
                raise
            session_id = min(self._ready, key=self.priority)
            del self._ready[session_id]
            self._running.add(session_id)
            self._spawn(self._process(session_id))

    async def _process(self, session_id: int) -> None:
        assert self._slots is not None
        more = False
        try:
            job = await asyncio.to_thread(self._load, session_id)
            if job is None:
                return
            try:
                outcome, deaths = await self._run(job)
            except WorkerDied as died:
                log.error(
                    "an update process died during update %s of session %s",
                    job.update_index,
                    session_id,
                )
                more = await asyncio.to_thread(
                    self._fail, job, "the update process died", True, died.deaths
                )
            except UpdatesUnavailable:
                raise  # not the update's fault: it stays pending and is tried again
            except Exception:
                error = traceback.format_exc()
                log.error(
                    "update %s of session %s failed:\n%s", job.update_index, session_id, error
                )
                more = await asyncio.to_thread(self._fail, job, error, False)
                self.failed += 1
            else:
                policy = decode(outcome["greedy_policy"], make_environment(job.environment))
                more = await asyncio.to_thread(self._commit, job, outcome, deaths)
                self.policies.put(session_id, job.update_index, policy)
                self.completed += 1
            processed = await asyncio.to_thread(self._processed_in_db, session_id)
            self._notify(session_id, processed)
        except asyncio.CancelledError:
            raise
        except UpdatesUnavailable as error:  # not the update's fault: it stays pending
            log.warning(
                "learner updates of session %s wait for the Dask scheduler: %s; retrying in %.0f s",
                session_id,
                error,
                RETRY_SECONDS,
            )
            self._retry_later(session_id)
        except Exception:
            # The database failed us: try this session again a little later.
            log.exception("learner updates of session %s could not be run; retrying", session_id)
            self._retry_later(session_id)
        finally:
            self._finish(session_id, more)

    def _finish(self, session_id: int, more: bool) -> None:
        """The session's update ended (``more``: it has further updates pending)."""
        assert self._slots is not None
        self._running.discard(session_id)
        self._slots.release()
        if more or session_id in self._again:
            self._again.discard(session_id)
            self._enqueue(session_id)
        else:  # nothing left to wait for (a mark from a race, or updates that failed)
            self._awaited.pop(session_id, None)

    def _retry_later(self, session_id: int) -> None:
        assert self._loop is not None
        self._loop.call_later(RETRY_SECONDS, self._enqueue, session_id)

    async def _run(self, job: Job) -> tuple[dict[str, Any], int]:
        """``run_update`` on the cluster or in an update process: its outcome, and how many
        processes died running it before it came back. Raises ``WorkerDied`` when the
        processes running it died (and gave no outcome)."""
        started = time.perf_counter()
        if self.cluster is not None:
            name = f"learner-update-{job.session_id}-{job.update_index}"
            outcome, deaths = await self.cluster.run(run_update, job.payload, name)
            self._costs.append(time.perf_counter() - started)
            return outcome, deaths
        executor = self._executor
        assert executor is not None
        try:
            outcome = await self._run_in_process(executor, job.payload)
        except BrokenProcessPool:
            self._replace_executor(executor)
            raise WorkerDied() from None
        self._costs.append(time.perf_counter() - started)
        return outcome, 0

    async def _run_in_process(self, executor: Executor, payload: dict[str, Any]) -> Any:
        """``run_update`` in an update process, its planner given this server's threads
        shared among the updates running with it."""
        self._in_flight += 1
        try:
            # The updates in flight, this one included, share the threads.
            threads = share_threads(self.threads, self._in_flight)
            return await asyncio.wrap_future(
                executor.submit(run_update, {**payload, "threads": threads})
            )
        finally:
            self._in_flight -= 1

    # -- capacity ----------------------------------------------------------------------------
    @property
    def slots(self) -> int:
        """Updates that run side by side on cores of their own: the cluster's worker threads,
        or the local update processes up to this machine's cores."""
        if self.cluster is not None:
            return max(1, self.workers)
        return max(1, min(self.workers, available_cores()))

    def capacity(self) -> Capacity | None:
        """Participants who can teach at once without waiting (``server.app.capacity``): from
        the mean wall time of the latest updates once there are enough, else from the
        reference updates timed at start; None before either."""
        if len(self._costs) >= LIVE_MINIMUM:
            seconds = float(np.mean(self._costs))
            measured_on = f"the latest {len(self._costs)} updates"
        elif self.reference_seconds is not None:
            seconds = self.reference_seconds
            measured_on = "the study's learners at start"
        else:
            return None
        return Capacity(
            participants=participants_at_once(seconds, self.slots, self.update_interval_seconds),
            update_seconds=seconds,
            slots=self.slots,
            update_interval_seconds=self.update_interval_seconds,
            measured_on=measured_on,
        )

    async def _measure_reference(self) -> None:
        """Once the update processes (or workers) are warm: time the reference updates on one
        of them, holding one slot meanwhile, and say the capacity."""
        assert self._slots is not None and self.reference_jobs is not None
        while not self.ready:
            await asyncio.sleep(0.5)
        request = {"jobs": self.reference_jobs}
        async with self._slots:
            try:
                if self.cluster is not None:
                    seconds, _ = await self.cluster.run(
                        measure_update_cost, request, "learner-update-reference"
                    )
                else:
                    assert self._executor is not None
                    seconds = await asyncio.wrap_future(
                        self._executor.submit(measure_update_cost, request)
                    )
            except asyncio.CancelledError:
                raise
            except Exception:
                log.exception("could not time the reference learner updates")
                return
        self.reference_seconds = float(seconds)
        capacity = self.capacity()
        assert capacity is not None
        log.info("%s", describe(capacity))

    def _replace_executor(self, broken: Executor) -> None:
        if self._stopping:  # no new workers while shutting down: they would outlive the server
            return
        if self._executor is broken:
            self._own_executor = True
            self._executor = new_executor(self.workers, self.niceness)
            self._start_workers()
            broken.shutdown(wait=False, cancel_futures=True)

    def _start_workers(self) -> None:
        """Start every update process now (a process pool starts one when a job finds none
        idle), so that they are warmed up before the first participant's update."""
        assert self._executor is not None
        for _ in range(self.workers):
            self._executor.submit(worker_ready)

    async def _await_warm(self) -> None:
        """Until every update process answers a job, which it takes only once it has loaded
        (or compiled) the learners' kernels: then the server is ready (``/api/health``)."""
        began = time.monotonic()
        log.info(
            "waiting for %d update process(es) to load the learners' compiled kernels (where "
            "numba's cache lacks them, as on a first start, they are compiled: about half a "
            "minute on two free cores); "
            "/api/health answers 503 until then",
            self.workers,
        )
        seen: set[int] = set()
        pool = self._executor
        while len(seen) < self.workers:
            executor = self._executor
            assert executor is not None
            if executor is not pool:  # replaced: its processes are new
                seen.clear()
                pool = executor
            try:
                jobs = [executor.submit(worker_ready, 0.2) for _ in range(self.workers)]
                for done in asyncio.as_completed([asyncio.wrap_future(job) for job in jobs]):
                    seen.add(await done)
                    self.warm_processes = min(len(seen), self.workers)
            except asyncio.CancelledError:
                raise
            except Exception:  # a broken pool is replaced by the dispatcher
                await asyncio.sleep(0.5)
        self.ready = True
        log.info(
            "update processes ready after %.1f s: the server is ready",
            time.monotonic() - began,
        )

    async def _watch_cluster(self) -> None:
        """Follow the cluster's workers: as many updates at once as they have threads, and
        the server ready (``/api/health``) once there are workers and every one is warm."""
        assert self.cluster is not None
        began = time.monotonic()
        log.info(
            "waiting for the workers of the Dask cluster at %s to load the learners' compiled "
            "kernels; /api/health answers 503 until then",
            self.cluster.address,
        )
        warming: asyncio.Task[None] | None = None
        while True:
            try:
                workers = await asyncio.to_thread(self.cluster.workers)
            except asyncio.CancelledError:
                raise
            except Exception as error:
                log.warning("could not ask the Dask cluster for its workers: %s", error)
                await asyncio.sleep(CLUSTER_WATCH_SECONDS)
                continue
            # At the start, and after the scheduler was replaced: its workers are to warm up.
            if not workers.warm_up_registered and (warming is None or warming.done()):
                warming = self._spawn(self._warm_up_cluster())
            self.workers = workers.threads
            self.warm_processes = workers.warm_threads
            self._resize(workers.threads)
            if not self.ready and workers.threads and workers.warm_threads == workers.threads:
                self.ready = True
                log.info(
                    "%d Dask worker thread(s) ready after %.1f s: the server is ready",
                    workers.threads,
                    time.monotonic() - began,
                )
            await asyncio.sleep(CLUSTER_WATCH_SECONDS if self.ready else 0.5)

    async def _warm_up_cluster(self) -> None:
        assert self.cluster is not None
        try:
            await asyncio.to_thread(self.cluster.warm_up_workers)
        except asyncio.CancelledError:
            raise
        except Exception:
            log.exception("could not ask the Dask cluster's workers to warm up")

    def _resize(self, capacity: int) -> None:
        """As many slots as ``capacity`` (at least one: with no worker yet, one update waits
        at the scheduler for the first)."""
        assert self._slots is not None
        capacity = max(1, capacity)
        change, self._capacity = capacity - self._capacity, capacity
        for _ in range(change):
            self._slots.release()
        if change < 0:
            self._spawn(self._take_slots(-change))

    async def _take_slots(self, count: int) -> None:
        assert self._slots is not None
        for _ in range(count):
            await self._slots.acquire()

    async def _rescan_forever(self) -> None:
        while True:
            try:
                pending = await asyncio.to_thread(self._pending_sessions)
            except Exception:
                log.exception("could not look for pending learner updates")
                pending = []
            self._enqueue_many(pending)
            await asyncio.sleep(RESCAN_SECONDS)

    # -- database work (in threads) ----------------------------------------------------------
    def _pending_sessions(self) -> list[int]:
        with self.db.read() as s:
            return list(
                s.scalars(
                    select(LearnerUpdate.session_id)
                    .where(LearnerUpdate.status == "pending")
                    .group_by(LearnerUpdate.session_id)
                    .order_by(func.min(LearnerUpdate.queued_at))
                )
            )

    def _processed_in_db(self, session_id: int) -> int:
        with self.db.read() as s:
            value = s.scalar(
                select(LearningSession.updates_processed).where(LearningSession.id == session_id)
            )
        return -1 if value is None else int(value)

    def _load(self, session_id: int) -> Job | None:
        with self.db.read() as s:
            update = s.scalar(
                select(LearnerUpdate)
                .where(LearnerUpdate.session_id == session_id, LearnerUpdate.status == "pending")
                .order_by(LearnerUpdate.update_index)
                .limit(1)
            )
            if update is None:
                return None
            session = s.get(LearningSession, session_id)
            if session is None:
                return None  # erased since the update was read
            base = s.execute(
                select(LearnerUpdate.through_event_id, LearnerUpdate.learner_state)
                .where(
                    LearnerUpdate.session_id == session_id,
                    LearnerUpdate.status == "done",
                    LearnerUpdate.learner_state.is_not(None),
                    LearnerUpdate.update_index < update.update_index,
                )
                .order_by(LearnerUpdate.update_index.desc())
                .limit(1)
            ).first()
            since = base.through_event_id if base is not None else 0
            rows = s.execute(
                select(
                    Event.record,
                    Event.task,
                    Event.state,
                    Event.action,
                    Event.next_state,
                    Event.feedback,
                    Event.stay_state,
                )
                .where(
                    Event.session_id == session_id,
                    Event.id > since,
                    Event.id <= update.through_event_id,
                )
                .order_by(Event.id)
            ).all()
            payload = {
                "environment": session.environment,
                "learner": session.learner,
                "settings": self.learner_settings(session.learner),
                "seed": int(session.seed),
                "base_state": base.learner_state if base is not None else None,
                "records": records_of(rows),
                "fit": update.update_index > 0,
            }
            return Job(update.id, session_id, update.update_index, session.environment, payload)

    def _commit(self, job: Job, outcome: dict[str, Any], deaths: int = 0) -> bool:
        """Store the update's outcome (after ``deaths`` processes died running it, each an
        attempt, as ``_fail`` records one)."""
        with self.db.write() as s:
            update = s.get(LearnerUpdate, job.update_id)
            session = s.get(LearningSession, job.session_id)
            if update is None or session is None:
                return False  # the participant was erased while the update ran
            update.status = "done"
            update.finished_at = utcnow()
            update.attempts += 1 + deaths
            if deaths:
                update.error = "the update process died"
            for name in (
                "learner_state",
                "greedy_policy",
                "seconds",
                "objective",
                "steps",
                "normalized_return",
                "evaluation_seconds",
            ):
                setattr(update, name, outcome[name])
            session.updates_processed = max(session.updates_processed, job.update_index)
            session.policy_update = max(session.policy_update or 0, job.update_index)
            return session.updates_requested > session.updates_processed

    def _fail(self, job: Job, error: str, retry: bool, attempts: int = 1) -> bool:
        with self.db.write() as s:
            update = s.get(LearnerUpdate, job.update_id)
            session = s.get(LearningSession, job.session_id)
            if update is None or session is None:
                return False  # the participant was erased while the update ran
            update.attempts += attempts
            update.error = error
            if retry and update.attempts < MAX_ATTEMPTS:
                return True
            update.status = "failed"
            update.finished_at = utcnow()
            session.updates_processed = max(session.updates_processed, job.update_index)
            return session.updates_requested > session.updates_processed
