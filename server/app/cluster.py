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
server records those attempts and runs it again until ``MAX_ATTEMPTS``.
"""

from __future__ import annotations

import asyncio
import logging
import os
import sys
import uuid
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from distributed import KilledWorker, SchedulerPlugin, WorkerPlugin

from server.app.updates import UpdatesUnavailable, WorkerDied
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
    update process does when it starts (``server.learners.warmup``)."""

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
    from server.learners.warmup import warm_up

    try:
        seconds = warm_up()
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
        self.address = str(client.scheduler.address)
        self.timeout = 10.0
        self._futures: set[Future] = set()
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
        it. Raises the function's error, or ``WorkerDied``."""
        loop = asyncio.get_running_loop()
        outcome: asyncio.Future[tuple[Any, int]] = loop.create_future()
        if self.client.status == "closed":
            raise UpdatesUnavailable(f"no connection to the Dask scheduler at {self.address}")
        future = self.client.submit(
            function, {**payload, "threads": THREADS_PER_UPDATE}, key=f"{name}-{uuid.uuid4().hex}"
        )
        self._futures.add(future)

        def settle(done: Future) -> None:  # in the client's callback thread
            try:
                if done.status == "finished":
                    deaths = self.deaths(str(done.key))
                    answer: tuple[str, Any] = ("result", (done.result(), deaths))
                elif done.status == "error":
                    error = done.exception()
                    if isinstance(error, KilledWorker):
                        error = WorkerDied(error.allowed_failures + 1)
                    answer = ("error", error)
                else:  # cancelled: the client lost the scheduler (or was closed)
                    answer = ("error", UpdatesUnavailable(f"the update was {done.status}"))
            except BaseException as error:  # the scheduler was lost
                answer = ("error", UpdatesUnavailable(f"the Dask scheduler failed: {error!r}"))
            finally:
                self._futures.discard(done)
            if answer[0] == "error" and not isinstance(answer[1], Exception):
                answer = ("error", UpdatesUnavailable(f"the Dask scheduler gave {answer[1]!r}"))
            try:
                loop.call_soon_threadsafe(_settle, outcome, answer)
            except RuntimeError:  # the server's loop is closed: it stopped
                pass

        future.add_done_callback(settle)
        try:
            return await outcome
        except asyncio.CancelledError:
            if future.client.status != "closed":  # a closed client has cancelled it already
                future.cancel()
            raise

    def close(self) -> None:
        """Cancel the updates in flight (they stay pending in the database) and disconnect."""
        if self._futures and self.client.status != "closed":
            self.client.cancel(list(self._futures))
        self.client.close()


def _settle(outcome: asyncio.Future[Any], answer: tuple[str, Any]) -> None:
    if outcome.done():
        return
    if answer[0] == "result":
        outcome.set_result(answer[1])
    else:
        outcome.set_exception(answer[1])
