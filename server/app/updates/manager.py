"""Learner updates, off the request path.

An episode end commits its events and a pending ``learner_updates`` row, then hands the session
to the ``UpdateManager``. The manager runs each session's pending updates in order, one at a time
per session, in a pool of processes (``BAM_UPDATE_WORKERS``, at a lower CPU priority than the
server so that moves stay fast; an update running alone, with none waiting for a process,
splits its planner's tasks over ``BAM_UPDATE_THREADS`` threads, updates side by side share
them): the worker restores the learner from the latest saved state (or builds a new one),
replays the events since, updates it, stores its greedy policies and scores them (exact
normalised return). The server then commits the new learner state with the evaluation, and an
agent step waiting for that session's update goes on.

The order minimises what participants wait for. A session's updates are awaited from the moment
its agent's turn is next (the participant lets the agent try: ``expect``) or an agent step or the
page waits for them in agent mode (``wait``), until they are done, across the waiter's retries;
awaited sessions go first, the one awaited longest first (the longest wait is the one the
participant feels), and the others take turns in the order their updates were queued. Order
changes only between sessions: a session's updates run one at a time in episode order, each from
the learner state the one before saved, so the agent shown after episode k is the agent recorded
after episode k. No request but the agent step waits for an update: demonstrations, moves and
episode ends go on while the session's updates are pending.

A slot's next update is read from the database while its last one runs, and stored while the
next one runs (``PREPARED_PER_SLOT``), so the processes do not wait for the database. When a
process frees, the prepared update whose session is awaited longest takes it (``ProcessGate``),
so an update read before anyone waited for it goes first once someone does. A local process is
handed on in the process pool's own thread, the moment its update ends: the next update starts
without waiting for a turn of the event loop, which many participants' requests keep busy.

Pending updates are found again in the database when the server starts, so none is lost by a
restart. With ``BAM_UPDATE_SCHEDULER`` the same function runs on the workers of a Dask cluster
instead of the local processes (``server.app.updates.cluster``), in the same order.

Several servers may share one PostgreSQL database (docs/deployment.md). Each update is claimed
in the database before it runs, with a lease this server renews while it lives (``store``), so
an update runs on one server, and is taken over when its server dies; the servers tell each
other of stored updates, new pending ones and awaited agents (``notices``), so a waiter on one
server goes on when another stores its update, and the sessions awaited longest go first on
every server. SQLite has one server: it takes back every claim when it starts.

The manager puts together three parts: ``queue`` (the order and the waits), ``store`` (the
database work) and ``runners`` (the local processes or the cluster); it dispatches, and says
the capacity.

One module of about 550 lines: ``UpdateManager`` is the one class that hands each update
between those three parts, and its dispatch reads as one.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable
from concurrent.futures import Executor, ThreadPoolExecutor
from typing import TYPE_CHECKING, Any

import numpy as np

from server.app.storage.db import Database
from server.app.storage.periodic import one_server_at_a_time
from server.app.updates.capacity import (
    LIVE_MINIMUM,
    LIVE_UPDATES,
    Capacity,
    LongestUpdate,
    ServerSlots,
    UpdateCost,
    deployment_participants,
    describe,
    longest_of,
    participants_at_once,
    session_updates,
)
from server.app.updates.notices import Listener, channel_of
from server.app.updates.policies import PolicyCache, decode
from server.app.updates.pool import UpdatesUnavailable, WorkerDied
from server.app.updates.queue import ProcessGate, QueueState, UpdateQueue
from server.app.updates.runners import ClusterUpdates, LocalUpdates, Runner
from server.app.updates.servers import (
    ServerLoad,
    ServerRegistry,
    others_slots,
    server_name,
    slots_machine,
)
from server.app.updates.store import LEASE_SECONDS, Job, UpdateStore
from server.cores import available_cores
from server.domains import make as make_environment

if TYPE_CHECKING:
    from server.app.updates.cluster import UpdateCluster

log = logging.getLogger("bam_study.updates")

RESCAN_SECONDS = 30.0
RETRY_SECONDS = 5.0  # a session whose update could not be run (database, scheduler) waits
# Updates read from the database ahead of a free slot, per slot: a slot's next update is ready
# when its last one ends, and the storing of one overlaps the next one's run (120 simulated
# participants, SQLite, 2 cores: 10.8 updates a second against 10.0 without).
PREPARED_PER_SLOT = 1
REFERENCE = -1  # the session id the reference updates hold a process as (no session's)


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
        server_share: Callable[[threading.Event], float] | None = None,
        database_cpu: Callable[[], float] | None = None,
        server: str | None = None,
        lease_seconds: float = LEASE_SECONDS,
    ) -> None:
        self.policies = policies
        self.db = db
        self.server = server or server_name()  # this server's name in claims and ``servers``
        self.lease_seconds = lease_seconds
        self.store = UpdateStore(db, learner_settings, self.server, lease_seconds)
        # Several servers on one database (PostgreSQL): they tell each other (``notices``).
        self.shared = db is not None and not db.is_sqlite
        self.order = UpdateQueue(self.store.processed, self._share_awaited if self.shared else None)
        self.registry = ServerRegistry(db, self.server)
        # The other live servers' update slots with their costs, as their latest heartbeats
        # said (read at this server's own heartbeats), and where this server's run.
        self._others: list[ServerSlots] = []
        self.machine = slots_machine(cluster.address if cluster is not None else None)
        self._listener: Listener | None = None
        # The notices this server sends outside a transaction of its own, off the event loop.
        self._announcing: ThreadPoolExecutor | None = None
        self.cluster = cluster  # updates on a Dask cluster (server.app.updates.cluster), not a pool
        self.runner: Runner = (
            ClusterUpdates(cluster, workers, self._resize)
            if cluster is not None
            else LocalUpdates(workers, niceness, threads, executor, self._waiting_for_a_slot)
        )
        self._capacity = workers  # updates run at once: the slots
        # Sessions whose next update is being read from the database: it claims a process
        # the moment it is read (read from the process pool's thread too, an int).
        self._reading = 0
        # Updates under way: running on a slot, or read from the database and waiting for one,
        # or being stored (PREPARED_PER_SLOT per slot beyond the running one).
        self._slots: asyncio.Semaphore | None = None
        # Updates running in the processes (or on the cluster's workers): one per slot, the
        # most urgent prepared one next.
        self._processes: ProcessGate | None = None
        self._tasks: set[asyncio.Task[Any]] = set()
        self.completed = 0
        self.failed = 0
        # The capacity (server.app.updates.capacity): jobs timed once the runner is warm (none:
        # not measured at start), their mean wall time, and the wall times of the latest updates.
        self.update_interval_seconds = update_interval_seconds
        self.reference_jobs = reference_jobs
        self.reference_seconds: float | None = None
        self.reference_longest: LongestUpdate | None = None
        self._costs: deque[float] = deque(maxlen=LIVE_UPDATES)
        # The server's own work per update (capacity.py), where the update processes share
        # its cores: timed at start by ``server_share`` once the reference updates are, then
        # from this process's CPU time at the end of each of the latest updates.
        # A PostgreSQL server on this machine works for the requests too: its CPU time is
        # added to the marks (``database_cpu``, server.app.storage.database_cpu).
        self.server_share = server_share if cluster is None else None
        self.database_cpu = database_cpu
        self.reference_server_seconds: float | None = None
        self._cpu_marks: deque[float] = deque(maxlen=LIVE_UPDATES + 1)

    # -- what the server reads ---------------------------------------------------------------
    @property
    def ready(self) -> bool:
        """Every update process (or cluster worker) is warm: the server is ready."""
        return self.runner.ready

    @property
    def warm_processes(self) -> int:
        return self.runner.warm_processes

    @property
    def workers(self) -> int:
        return self.runner.workers

    @property
    def slots(self) -> int:
        """Updates that run side by side on cores of their own: the cluster's worker threads,
        or the local update processes up to this machine's cores."""
        return self.runner.slots

    @property
    def backlog(self) -> int:
        """Sessions waiting for a slot or being updated."""
        return self.order.backlog

    def queue(self) -> QueueState:
        """What the dashboard shows of the live queue."""
        return self.order.state(self._capacity, self.completed, self.failed)

    def _waiting_for_a_slot(self) -> int:
        """Sessions whose updates wait for a slot or are being read from the database to
        take one (an update that starts meanwhile shares the cores with theirs)."""
        return self.order.queued + self._reading

    def submit(self, session_ids: list[int]) -> None:
        """Thread-safe: these sessions have new pending updates (the other servers are told:
        whichever has a slot free first claims them)."""
        self.order.submit(session_ids)
        if self._announcing is not None and session_ids:
            self._announcing.submit(self._quietly, self.store.announce_pending, list(session_ids))

    def _share_awaited(self, session_id: int, target: int, since: float) -> None:
        """On the loop: a wait began here; the other servers' queues put the session first."""
        if self._announcing is not None:
            self._announcing.submit(
                self._quietly, self.store.await_update, session_id, target, since
            )

    @staticmethod
    def _quietly(work: Callable[..., None], *args: Any) -> None:
        try:
            work(*args)
        except Exception:  # a notice lost costs time only (the poll and the rescan)
            log.exception("could not tell the other servers")

    def _heard(self, notice: dict[str, Any]) -> None:
        """On the loop: a notice from another server (``notices``)."""
        try:
            if "processed" in notice:
                self.order.notify(int(notice["processed"]), int(notice["update"]))
            elif "pending" in notice:
                self.order.enqueue_many([int(i) for i in notice["pending"]])
            elif "awaited" in notice:
                self.order.mark_awaited(
                    int(notice["awaited"]), int(notice["update"]), float(notice["since"])
                )
        except (KeyError, TypeError, ValueError):
            log.warning("a notice not understood: %r", notice)

    def load(self) -> ServerLoad:
        """What this server's heartbeat says of it."""
        capacity = self.capacity()
        return ServerLoad(
            update_slots=self.slots,
            updates_running=self.order.updating,
            updates_completed=self.completed,
            updates_failed=self.failed,
            participants_at_once=capacity.participants if capacity is not None else None,
            machine=self.machine,
            cores=available_cores() if self.cluster is None else None,
            update_seconds=capacity.update_seconds if capacity is not None else None,
            server_seconds=capacity.server_seconds if capacity is not None else None,
        )

    def expect(self, session_id: int, target: int) -> None:
        """Thread-safe: someone waits for the session's update ``target`` from now on."""
        self.order.expect(session_id, target)

    async def wait(
        self, session_id: int, target: int, timeout: float, awaited: bool = True
    ) -> bool:
        """Wait until the session's update ``target`` is processed (``UpdateQueue.wait``)."""
        return await self.order.wait(session_id, target, timeout, awaited)

    # -- lifecycle ---------------------------------------------------------------------------
    async def start(self) -> None:
        self.order.start()
        if self.shared:
            self.store.channel = await asyncio.to_thread(channel_of, self.db.engine)
            self._listener = Listener(self.db.engine, self.store.channel, self.server, self._heard)
            self._listener.start(asyncio.get_running_loop())
            self._announcing = ThreadPoolExecutor(1, thread_name_prefix="update-notices-out")
        else:  # the only server (a second one is refused at start): every claim is stale
            await asyncio.to_thread(self.store.release_all, True)
        self._slots = asyncio.Semaphore(self._capacity * (1 + PREPARED_PER_SLOT))
        self._processes = ProcessGate(self._capacity, self.order.priority)
        await asyncio.to_thread(self.registry.register, self.load())
        self.runner.start(self._spawn)
        self._spawn(self._dispatch())
        self._spawn(self._rescan_forever())
        self._spawn(self._heartbeat_forever())
        if self.reference_jobs:
            self._spawn(self._measure_reference())

    async def stop(self) -> None:
        for task in list(self._tasks):
            task.cancel()
        for task in list(self._tasks):
            try:
                await task
            except (asyncio.CancelledError, Exception):
                pass
        self.order.stop()
        await self.runner.stop()
        if self._listener is not None:
            await asyncio.to_thread(self._listener.stop)
        if self._announcing is not None:
            self._announcing.shutdown(wait=True)
            self._announcing = None
        try:  # the claims go back at once (a restarted or another server takes them)
            await asyncio.to_thread(self.store.release_all)
            await asyncio.to_thread(self.registry.stopped)
        except Exception:
            log.exception("could not give back this server's claims on learner updates")

    @property
    def heartbeat_seconds(self) -> float:
        """How often the server renews its leases and says its load: a third of the lease."""
        return self.lease_seconds / 3

    async def _heartbeat_forever(self) -> None:
        while True:
            await asyncio.sleep(self.heartbeat_seconds)
            try:
                await asyncio.to_thread(self.store.renew)
                await asyncio.to_thread(self.registry.beat, self.load())
                if self.shared:
                    self._others = await asyncio.to_thread(
                        others_slots, self.db, self.server, self.lease_seconds
                    )
            except Exception:
                log.exception("could not renew this server's claims on learner updates")

    def _spawn(self, coroutine: Any) -> asyncio.Task[Any]:
        task = asyncio.ensure_future(coroutine)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    # -- dispatching -------------------------------------------------------------------------
    async def _dispatch(self) -> None:
        assert self._slots is not None
        while True:
            await self._slots.acquire()
            try:
                session_id = await self.order.take()
            except BaseException:
                self._slots.release()
                raise
            self._spawn(self._process(session_id))

    async def _process(self, session_id: int) -> None:
        more = False
        try:
            self._reading += 1
            try:
                job = await asyncio.to_thread(self.store.load, session_id)
            finally:
                # No await between here and the gate's claim (``runner.run``): the update
                # is counted as reading or as waiting for a process, never as neither.
                self._reading -= 1
            if job is None:
                return
            try:
                outcome, deaths = await self._run(job)
            except UpdatesUnavailable:
                # Not the update's fault: it stays pending, for this server or another.
                await asyncio.to_thread(self.store.release, job)
                raise
            except WorkerDied as died:
                log.error(
                    "an update process died during update %s of session %s",
                    job.update_index,
                    session_id,
                )
                more = await asyncio.to_thread(
                    self.store.fail, job, "the update process died", True, died.deaths
                )
            except Exception:
                error = traceback.format_exc()
                log.error(
                    "update %s of session %s failed:\n%s", job.update_index, session_id, error
                )
                more = await asyncio.to_thread(self.store.fail, job, error, False)
                self.failed += 1
            else:
                policy = decode(outcome["greedy_policy"], make_environment(job.environment))
                stored = await asyncio.to_thread(self.store.commit, job, outcome, deaths)
                more = stored.more
                if stored.stored:
                    self.policies.put(session_id, job.update_index, policy)
                    self.completed += 1
                else:
                    log.warning(
                        "update %s of session %s was taken over by another server (this "
                        "server's lease expired): its result here is not stored",
                        job.update_index,
                        session_id,
                    )
            processed = await asyncio.to_thread(self.store.processed, session_id)
            self.order.notify(session_id, processed)
        except asyncio.CancelledError:
            raise
        except UpdatesUnavailable as error:  # not the update's fault: it stays pending
            log.warning(
                "learner updates of session %s wait for the Dask scheduler: %s; retrying in %.0f s",
                session_id,
                error,
                RETRY_SECONDS,
            )
            self.order.retry_later(session_id, RETRY_SECONDS)
        except Exception:
            # The database failed us: try this session again a little later.
            log.exception("learner updates of session %s could not be run; retrying", session_id)
            self.order.retry_later(session_id, RETRY_SECONDS)
        finally:
            self._finish(session_id, more)

    def _finish(self, session_id: int, more: bool) -> None:
        """The session's update ended (``more``: it has further updates pending)."""
        assert self._slots is not None
        self._slots.release()
        self.order.finish(session_id, more)

    async def _run(self, job: Job) -> tuple[dict[str, Any], int]:
        """``run_update`` where the runner runs it, once a process is the job's (the most
        urgent prepared update first, ``ProcessGate``), timed for the capacity."""
        assert self._processes is not None
        name = f"learner-update-{job.session_id}-{job.update_index}"
        outcome, deaths, seconds = await self.runner.run(
            job.payload, name, self._processes, job.session_id
        )
        # Where the update processes share the server's cores, an update's CPU time: its wall
        # time there counts the moments the server's work (or a database's) held its core,
        # which the capacity counts apart (``server_seconds``).
        shared = self.cluster is None and "cpu_seconds" in outcome
        self._costs.append(float(outcome["cpu_seconds"]) if shared else seconds)
        database = self.database_cpu() if self.database_cpu is not None else 0.0
        self._cpu_marks.append(time.process_time() + database)
        return outcome, deaths

    async def _rescan_forever(self) -> None:
        """Pending updates nobody holds (left by a restart, or by a server that died, once its
        lease expired), with who awaits them, every ``RESCAN_SECONDS`` or each lease."""
        while True:
            try:
                pending = await asyncio.to_thread(self.store.pending_sessions)
            except Exception:
                log.exception("could not look for pending learner updates")
                pending = []
            for session in pending:
                if session.awaited_since is not None and session.awaited_update is not None:
                    self.order.mark_awaited(
                        session.session_id, session.awaited_update, session.awaited_since
                    )
                else:
                    self.order.enqueue(session.session_id)
            await asyncio.sleep(min(RESCAN_SECONDS, self.lease_seconds))

    # -- capacity ----------------------------------------------------------------------------
    def capacity(self) -> Capacity | None:
        """Participants who can teach at once without waiting (``server.app.updates.capacity``):
        from the mean wall time of the latest updates once there are enough, else from the
        reference updates timed at start; None before either."""
        server: float | None
        if len(self._costs) >= LIVE_MINIMUM:
            seconds = float(np.mean(self._costs))
            measured_on = f"the latest {len(self._costs)} updates"
            marks = self._cpu_marks
            shared = self.cluster is None and len(marks) > 1
            server = (marks[-1] - marks[0]) / (len(marks) - 1) if shared else None
        elif self.reference_seconds is not None and not self._timing_server_share:
            seconds = self.reference_seconds
            measured_on = "the study's learners at start"
            server = self.reference_server_seconds
        else:
            return None
        return Capacity(
            participants=participants_at_once(
                seconds,
                self.slots,
                self.update_interval_seconds,
                server_seconds=server or 0.0,
                cores=None if server is None else available_cores(),
            ),
            update_seconds=seconds,
            slots=self.slots,
            update_interval_seconds=self.update_interval_seconds,
            measured_on=measured_on,
            longest_update=self.reference_longest,
            server_seconds=server,
        )

    def deployment_capacity(self) -> Capacity | None:
        """The capacity of the whole deployment: this server's slots with the other live
        servers' (their heartbeats'), each machine's cores counted once
        (``capacity.deployment_participants``); None before this server's own is known. One
        server: ``capacity()``."""
        own = self.capacity()
        if own is None or not self._others:
            return own
        mine = ServerSlots(
            machine=self.machine,
            slots=self.slots,
            cores=available_cores() if self.cluster is None else None,
            update_seconds=own.update_seconds,
            server_seconds=own.server_seconds,
        )
        participants, slots = deployment_participants(
            [mine, *self._others], self.update_interval_seconds
        )
        return dataclasses.replace(
            own,
            participants=participants,
            slots=slots,
            measured_on=f"{own.measured_on}, with the deployment's other servers",
        )

    @property
    def _timing_server_share(self) -> bool:
        """The server's own work per update is to be timed at start and is not yet."""
        return self.server_share is not None and self.reference_server_seconds is None

    async def _measure_reference(self) -> None:
        """Once the runner is warm: time the reference updates on one of its processes (or
        workers), a session at a time, each holding one slot meanwhile (a server stopped
        meanwhile waits for one session's updates, not for all), and say the capacity."""
        assert self._processes is not None and self.reference_jobs is not None
        while not self.ready:
            await asyncio.sleep(0.5)
        async with one_server_at_a_time(self.db, "capacity"):
            await self._time_reference()

    async def _time_reference(self) -> None:
        """The reference updates timed (``_measure_reference``), alone on the deployment."""
        assert self._processes is not None and self.reference_jobs is not None
        total = updates = 0.0
        costs: list[UpdateCost] = []
        for index, session in enumerate(self.reference_jobs):
            async with self._processes.holding(REFERENCE):
                try:
                    cost = await self.runner.measure({"jobs": [session], "warm": index == 0})
                except asyncio.CancelledError:
                    raise
                except Exception:
                    log.exception("could not time the reference learner updates")
                    return
            count = len(session_updates(session))
            total += cost.mean_seconds * count
            updates += count
            costs.append(cost)
        self.reference_longest = longest_of(costs)
        self.reference_seconds = total / updates
        if self.server_share is not None:
            stop = threading.Event()  # set: the server is stopping, the timing ends
            try:
                self.reference_server_seconds = await asyncio.to_thread(self.server_share, stop)
            except asyncio.CancelledError:
                stop.set()
                raise
            except Exception:
                log.exception("could not time the server's own work per update")
                self.server_share = None  # the capacity is stated without it
        capacity = self.capacity()
        assert capacity is not None
        log.info("%s", describe(capacity))

    def _resize(self, capacity: int) -> None:
        """As many slots as ``capacity`` (at least one: with no worker yet, one update waits
        at the scheduler for the first)."""
        assert self._slots is not None and self._processes is not None
        capacity = max(1, capacity)
        change, self._capacity = capacity - self._capacity, capacity
        self._processes.resize(change)
        for _ in range(change * (1 + PREPARED_PER_SLOT)):
            self._slots.release()
        if change < 0:
            self._spawn(self._take(self._slots, -change * (1 + PREPARED_PER_SLOT)))

    async def _take(self, semaphore: asyncio.Semaphore, count: int) -> None:
        for _ in range(count):
            await semaphore.acquire()
