"""Learner updates on a Dask distributed cluster (``BAM_UPDATE_SCHEDULER``).

The ``UpdateManager`` keeps its order (one update at a time per learning session, waiting
agents first) and its database work; only where ``run_update`` runs changes: each update's
job (the learner's saved state and the events since, a few KB) goes to the cluster, whose
workers run the same function a local update process runs, and its result comes back to be
committed as a local one is. The workers load the learners' compiled kernels when they join
(``WarmUp``, a worker plugin), and the server counts as ready once every worker has.

A worker that dies during an update: the scheduler gives the update to another worker, and
the server records the death as one failed attempt, as it does for a local process that
dies. An update whose workers die more often than the scheduler allows
(``distributed.scheduler.allowed-failures``, 3 by default) comes back as ``KilledWorker``: the
server records those attempts and runs it again until ``store.MAX_ATTEMPTS``.
"""

from __future__ import annotations

import asyncio
import logging
import os
import sys
import threading
import uuid
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from distributed import KilledWorker, SchedulerPlugin, WorkerPlugin

from server.app.updates.pool import UpdatesUnavailable, WorkerDied
from server.dask_client import connect

if TYPE_CHECKING:
    from distributed import Client, Future, Worker
    from distributed.scheduler import Scheduler

log = logging.getLogger("bam_study.updates")

PLUGIN_NAME = "bam-study-warm-up"
DEATHS_PLUGIN = "bam-study-deaths"
DEATHS_HANDLER = "bam_study_deaths"  # the scheduler's operation that DeathCounts adds
# One planner thread per update: a worker runs as many updates at once as it has threads.
THREADS_PER_UPDATE = 1

_warm = False  # in a worker process: it has been through its warm-up


class WarmUp(WorkerPlugin):
    """Loads (or compiles) the learners' kernels in every worker when it joins, as a local
    update process does when it starts (``server.app.updates.warmup``)."""

    name = PLUGIN_NAME

    async def setup(self, worker: Worker) -> None:
        # In a thread: the worker keeps answering its scheduler while the kernels load.
        await asyncio.to_thread(warm_this_process)


def warm_this_process() -> None:
    """Warm up this process once. An error is printed, as a local update process prints it,
    and the worker counts as warm all the same: an update would meet the same error and report
    it for its session."""
    global _warm
    if _warm:
        return
    from server.app.updates.compiling import warm_up_here

    try:
        seconds = warm_up_here()
    except Exception:
        import traceback

        traceback.print_exc()
    else:
        print(f"update worker {os.getpid()} ready in {seconds:.1f} s", file=sys.stderr)
    _warm = True


def is_warm() -> bool:
    """In a worker, through ``Client.run``: has it been through its warm-up?"""
    return _warm


class DeathCounts(SchedulerPlugin):
    """On the scheduler: adds the operation ``DEATHS_HANDLER``, how often a worker died while
    running a task (``UpdateCluster.deaths``)."""

    name = DEATHS_PLUGIN
    idempotent = True  # registered again on a scheduler that has it: nothing changes

    async def start(self, scheduler: Scheduler) -> None:
        def deaths(key: str) -> int:
            task = scheduler.tasks.get(key)
            return 0 if task is None else int(task.suspicious)

        scheduler.handlers[DEATHS_HANDLER] = deaths


@dataclass
class Workers:
    threads: int  # updates the cluster runs at once
    warm_threads: int  # of them, on workers that have loaded the kernels
    warm_up_registered: bool = True  # the scheduler has the WarmUp plugin (a new one has not)


class UpdateCluster:
    """The server's client of the cluster that runs its learner updates."""

    def __init__(self, client: Client) -> None:
        self.client = client
        scheduler = client.scheduler
        if scheduler is None:
            raise UpdatesUnavailable("the Dask client has no scheduler")
        self.address = str(scheduler.address)
        self.timeout = 10.0
        self._lock = threading.Lock()
        # The tasks the server waits for: the future, the server's loop, and what it awaits.
        self._in_flight: dict[
            str, tuple[Future, asyncio.AbstractEventLoop, asyncio.Future[None]]
        ] = {}
        self._counted_on: str | None = None  # the scheduler (its id) that has DeathCounts
        self._warmed_on: str | None = None  # the scheduler that has the WarmUp plugin

    @classmethod
    def connect(cls, address: str, timeout: float = 10.0) -> UpdateCluster:
        """Raises ``server.dask_client.SchedulerError`` (one line) if it cannot connect."""
        cluster = cls(connect(address, timeout, what="BAM_UPDATE_SCHEDULER"))
        cluster.timeout = timeout
        cluster.count_deaths()
        return cluster

    def scheduler_id(self) -> str:
        """Blocking: the id of the scheduler the client is connected to (a restarted scheduler
        has a new one)."""
        return str(self.client.scheduler_info(n_workers=0)["id"])

    def count_deaths(self) -> None:
        """Blocking: the scheduler counts the deaths for ``deaths`` (once per scheduler)."""
        scheduler = self.scheduler_id()
        if self._counted_on != scheduler:
            self.client.register_plugin(DeathCounts(), name=DEATHS_PLUGIN)
            self._counted_on = scheduler

    def deaths(self, key: str) -> int:
        """Blocking: how often a worker died while running the task ``key``."""
        self.count_deaths()
        return int(self.client.sync(getattr(self.client.scheduler, DEATHS_HANDLER), key=key))

    def warm_up_workers(self) -> None:
        """Blocking, until the workers there now have warmed up; those that join later warm up
        as they join."""
        scheduler = self.scheduler_id()
        self.client.register_plugin(WarmUp(), name=PLUGIN_NAME)
        self._warmed_on = scheduler

    def _reconnect(self) -> None:
        """A client closed (the scheduler was out of reach for longer than it waits for it to
        come back) is replaced by a new one, when the scheduler answers again."""
        if self.client.status != "closed":
            return
        self._abandon()
        self.client = connect(self.address, self.timeout, what="BAM_UPDATE_SCHEDULER")
        log.info("reconnected to the Dask scheduler at %s", self.address)

    def workers(self) -> Workers:
        """Blocking (call it in a thread); reconnects to the scheduler if the client has given
        up on it."""
        self._reconnect()
        threads = self.client.nthreads()
        warm = self.client.run(is_warm, on_error="return") if threads else {}
        return Workers(
            threads=sum(threads.values()),
            warm_threads=sum(n for address, n in threads.items() if warm.get(address) is True),
            warm_up_registered=self._warmed_on == self.scheduler_id(),
        )

    async def run(self, function: Any, payload: dict[str, Any], name: str) -> tuple[Any, int]:
        """``function(payload)`` on a worker, as a task named ``name`` (and a unique suffix,
        as the cluster's dashboard shows it): its result, and how many workers died running
        it. Raises the function's error, ``WorkerDied``, or ``UpdatesUnavailable`` when the
        scheduler was out of reach (the update stays pending and is run again)."""
        client = self.client
        # Only a connected client: one reconnecting or closing takes a task and never settles
        # it (seen: an update submitted as the client closed waited for ever).
        if client.status != "running":
            raise UpdatesUnavailable(
                f"no connection to the Dask scheduler at {self.address} (the client is "
                f"{client.status})"
            )
        loop = asyncio.get_running_loop()
        done: asyncio.Future[None] = loop.create_future()
        key = f"{name}-{uuid.uuid4().hex}"
        future = client.submit(function, {**payload, "threads": THREADS_PER_UPDATE}, key=key)
        with self._lock:
            self._in_flight[key] = (future, loop, done)
        # Dask runs every future's callbacks in one thread: this one only wakes the server's
        # loop, and what asks the scheduler (the deaths) runs in a thread of the server's own.
        future.add_done_callback(lambda _: self._wake(key))
        try:
            await done
        except asyncio.CancelledError:
            if client.status != "closed":  # a closed client has cancelled it already
                future.cancel()
            raise
        finally:
            with self._lock:
                self._in_flight.pop(key, None)
        return await asyncio.to_thread(self._outcome, future, key)

    def _wake(self, key: str) -> None:
        """From any thread: the server's wait for the task ``key`` ends."""
        with self._lock:
            entry = self._in_flight.get(key)
        if entry is None:
            return
        _, loop, done = entry
        try:
            loop.call_soon_threadsafe(_set_done, done)
        except RuntimeError:  # the server's loop is closed: it stopped
            pass

    def _abandon(self) -> None:
        """The client is closed: the tasks it held will never settle; their updates stay
        pending and are run again."""
        with self._lock:
            keys = list(self._in_flight)
        for key in keys:
            self._wake(key)

    def _outcome(self, future: Future, key: str) -> tuple[Any, int]:
        """Blocking: the ended task's result and deaths, or the error it ended with."""
        status = future.status
        try:
            if status == "finished":
                return future.result(), self.deaths(key)
            error = future.exception() if status == "error" else None
        except Exception as lost:
            raise UpdatesUnavailable(f"the Dask scheduler failed: {lost!r}") from None
        if status != "error":  # cancelled, or left pending by a closed client
            raise UpdatesUnavailable(f"the update was lost with the scheduler ({status})")
        if isinstance(error, KilledWorker):
            raise WorkerDied(error.allowed_failures + 1)
        if isinstance(error, Exception):
            raise error
        raise UpdatesUnavailable(f"the Dask scheduler gave {error!r}")

    def close(self) -> None:
        """Cancel the updates in flight (they stay pending in the database) and disconnect."""
        with self._lock:
            futures = [future for future, _, _ in self._in_flight.values()]
        if futures and self.client.status != "closed":
            self.client.cancel(futures)
        self.client.close()
        self._abandon()


def _set_done(done: asyncio.Future[None]) -> None:
    if not done.done():
        done.set_result(None)
