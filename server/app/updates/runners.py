"""Where the learner updates run: a pool of local processes (``LocalUpdates``) or the workers of
a Dask cluster (``ClusterUpdates``, ``BAM_UPDATE_SCHEDULER``). Both run ``run_update`` on a job's
payload, say when they are warm (the server is ready once they are) and how many updates they
run side by side; the manager (``server.app.updates.manager``) keeps the order."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
import threading
import time
from collections.abc import Callable, Coroutine, Iterator
from concurrent.futures import Executor, Future
from concurrent.futures.process import BrokenProcessPool
from typing import TYPE_CHECKING, Any, Protocol

from server.app.updates.capacity import UpdateCost, measure_updates
from server.app.updates.pool import WorkerDied, new_executor
from server.app.updates.queue import ProcessGate
from server.app.updates.worker import run_update, worker_ready
from server.cores import available_cores, share_threads
from server.learners.compile_notice import COMPILE_TIME

if TYPE_CHECKING:
    from server.app.updates.cluster import UpdateCluster

log = logging.getLogger("bam_study.updates")

CLUSTER_WATCH_SECONDS = 10.0  # how often a ready server asks its Dask cluster about the workers

Spawn = Callable[[Coroutine[Any, Any, Any]], "asyncio.Task[Any]"]


class Runner(Protocol):
    workers: int  # update processes, or the cluster's worker threads
    warm_processes: int  # of those, known to have loaded the learners' kernels
    ready: bool  # every one is warm

    @property
    def slots(self) -> int: ...

    def start(self, spawn: Spawn) -> None: ...

    async def run(
        self, payload: dict[str, Any], name: str, gate: ProcessGate, session_id: int
    ) -> tuple[dict[str, Any], int, float]: ...

    async def measure(self, request: dict[str, Any]) -> UpdateCost: ...

    async def stop(self) -> None: ...


class LocalUpdates:
    """Updates in a pool of processes on this machine (``BAM_UPDATE_WORKERS``), at a lower CPU
    priority than the server; an update running alone, with none waiting for a process, splits
    its planner's tasks over ``BAM_UPDATE_THREADS`` threads; updates side by side, or one with
    others waiting, share them."""

    def __init__(
        self,
        workers: int,
        niceness: int,
        threads: int,
        executor: Executor | None = None,
        queued: Callable[[], int] = lambda: 0,
    ) -> None:
        self.workers = workers
        self.niceness = niceness
        self.threads = threads
        self.executor = executor
        self.queued = queued  # sessions whose updates wait for a slot (or are being read)
        self._own_executor = executor is None
        self._in_flight = 0  # updates submitted to the processes and not yet returned
        self._lock = threading.Lock()  # guards _in_flight: updates start in the pool's thread
        self._stopping = False
        self.warm_processes = 0
        self.ready = False

    @property
    def slots(self) -> int:
        """Update processes up to this machine's cores."""
        return max(1, min(self.workers, available_cores()))

    def start(self, spawn: Spawn) -> None:
        self._stopping = False
        if self.executor is None:
            self.executor = new_executor(self.workers, self.niceness)
            self._start_workers()
        spawn(self._await_warm())

    async def stop(self) -> None:
        self._stopping = True
        if self._own_executor and self.executor is not None:
            executor, self.executor = self.executor, None
            # Updates not started stay pending in the database and run after the next start.
            # The processes are waited for (one in an update finishes it), and the pool's
            # queues released: a server stopped by a signal ends right after this, without
            # Python's exit handlers, and their semaphores would be reported leaked. Processes
            # still warming up (compiling, minutes on a first start) have no update to finish:
            # they are ended, or the stop would wait for their compile.
            # Their jobs are then failed by the pool (BrokenProcessPool), not cancelled: a
            # job cancelled while the pool breaks raises in Python 3.11's pool thread.
            warming = not self.ready
            if warming:
                _end_processes(executor)
            await asyncio.to_thread(executor.shutdown, wait=True, cancel_futures=not warming)

    async def run(
        self, payload: dict[str, Any], name: str, gate: ProcessGate, session_id: int
    ) -> tuple[dict[str, Any], int, float]:
        """``run_update`` in an update process once ``gate`` hands the session one, its
        planner given this server's threads shared among the updates running with it: its
        outcome, no death, and its wall time. The process is handed on where its update
        ends, in the pool's own thread (``ProcessGate``). Raises ``WorkerDied`` when the
        process running it died (the pool is replaced)."""
        loop = asyncio.get_running_loop()
        result: asyncio.Future[tuple[Future[Any], float]] = loop.create_future()
        used: list[Executor] = []  # the pool it was submitted to

        def settle(future: Future[Any], seconds: float) -> None:
            """In the thread that saw the update end (or fail to start)."""
            gate.release()  # the next prepared update starts now, in this thread
            try:
                loop.call_soon_threadsafe(_deliver, result, future, seconds)
            except RuntimeError:  # the loop is closed: the server stopped
                pass

        def begin() -> None:
            """In whichever thread handed this update a process."""
            started = time.perf_counter()
            try:
                future = self._submit(payload, used, waiting=gate.waiting + self.queued())
            except BaseException as error:  # a broken or stopped pool
                failed: Future[Any] = Future()
                failed.set_exception(error)
                settle(failed, 0.0)
                return
            future.add_done_callback(lambda done: settle(done, time.perf_counter() - started))

        claim = gate.claim(session_id, begin)
        try:
            future, seconds = await result
        except asyncio.CancelledError:
            # Not started: it never will be. Started: it runs to its end, which frees its process.
            gate.withdraw(claim)
            raise
        try:
            outcome = future.result()
        except BrokenProcessPool:
            self._replace_executor(used[0])  # the pool it was submitted to broke
            raise WorkerDied() from None
        return outcome, 0, seconds

    def _submit(self, payload: dict[str, Any], used: list[Executor], waiting: int) -> Future[Any]:
        """``run_update`` submitted to the pool (noted in ``used``), with the planner threads
        its share: the updates in flight, this one included, share them, and every slot's
        update does while ``waiting`` other updates wait for one. An update given the spare
        cores while others wait has them taken by the next update within moments, and its
        planner's extra threads, which spin between passes, then take CPU from that update
        (200 simulated participants, AVX-512 AMD EPYC, 2 cores: such updates used twice
        their own thread's CPU, 9% of all the updates' CPU)."""
        executor = self.executor
        if executor is None:
            raise RuntimeError("the update processes have stopped")
        used.append(executor)
        with self._lock:
            self._in_flight += 1
            sharers = max(self._in_flight, self.slots) if waiting else self._in_flight
            threads = share_threads(self.threads, sharers)
        try:
            future = executor.submit(run_update, {**payload, "threads": threads})
        except BaseException:
            self._finished()
            raise
        future.add_done_callback(lambda _: self._finished())
        return future

    def _finished(self) -> None:
        with self._lock:
            self._in_flight -= 1

    async def measure(self, request: dict[str, Any]) -> UpdateCost:
        assert self.executor is not None
        cost: UpdateCost = await asyncio.wrap_future(self.executor.submit(measure_updates, request))
        return cost

    def _replace_executor(self, broken: Executor) -> None:
        if self._stopping:  # no new workers while shutting down: they would outlive the server
            return
        if self.executor is broken:
            self._own_executor = True
            self.executor = new_executor(self.workers, self.niceness)
            self._start_workers()
            broken.shutdown(wait=False, cancel_futures=True)

    def _start_workers(self) -> None:
        """Start every update process now (a process pool starts one when a job finds none
        idle), so that they are warmed up before the first participant's update."""
        assert self.executor is not None
        with processes_born_deaf_to_ctrl_c():
            for _ in range(self.workers):
                self.executor.submit(worker_ready)  # each submit starts one process

    async def _await_warm(self) -> None:
        """Until every update process answers a job, which it takes only once it has loaded
        (or compiled) the learners' kernels: then the server is ready (``/api/health``)."""
        began = time.monotonic()
        log.info(
            "waiting for %d update process(es) to load the learners' compiled kernels (where "
            "numba's cache lacks them, as on a first start, they are compiled: %s in all, "
            "each kernel by one process, the processes side by side); /api/health answers 503 until then",
            self.workers,
            COMPILE_TIME,
        )
        seen: set[int] = set()
        pool = self.executor
        while len(seen) < self.workers:
            executor = self.executor
            assert executor is not None
            if executor is not pool:  # replaced: its processes are new
                seen.clear()
                pool = executor
            answers: list[asyncio.Future[int]] = []
            try:
                jobs = [executor.submit(worker_ready, 0.2) for _ in range(self.workers)]
                answers = [asyncio.wrap_future(job) for job in jobs]
                for done in asyncio.as_completed(answers):
                    seen.add(await done)
                    self.warm_processes = min(len(seen), self.workers)
            except asyncio.CancelledError:
                # The server stops: the jobs' answers (a broken pool's error, once its
                # processes are ended) are nobody's, and asyncio would log each as lost.
                # Not cancelled: that would cancel the pool's jobs too (above).
                for answer in answers:
                    answer.add_done_callback(_read)
                raise
            except Exception:  # a broken pool is replaced when an update finds it broken
                await asyncio.sleep(0.5)
        self.ready = True
        log.info(
            "update processes ready after %.1f s: the server is ready",
            time.monotonic() - began,
        )


def _read(answer: asyncio.Future[Any]) -> None:
    """An answer nobody waits for any more, read so that asyncio does not log it as lost."""
    if not answer.cancelled():
        answer.exception()


@contextlib.contextmanager
def processes_born_deaf_to_ctrl_c() -> Iterator[None]:
    """Processes started meanwhile ignore SIGINT from their first instruction: an ignored
    signal stays ignored across ``exec``, and Python then installs no KeyboardInterrupt handler.
    Ctrl-C reaches the terminal's whole process group; an update process interrupted while it
    imports, before ``worker_init`` ignores SIGINT itself, printed a traceback. Only the main
    thread may change a signal's handler: elsewhere nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    handler = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, handler)


def _end_processes(executor: Executor) -> None:
    """End a process pool's processes at once (SIGTERM), whatever they are doing."""
    terminate = getattr(executor, "terminate_workers", None)  # Python 3.14
    if terminate is not None:
        terminate()
        return
    processes = getattr(executor, "_processes", None) or {}
    for process in list(processes.values()):
        if process.is_alive():
            process.terminate()


class ClusterUpdates:
    """Updates on the workers of a Dask cluster (``server.app.updates.cluster``): as many side
    by side as the workers have threads, followed as workers come and go (``resize``)."""

    def __init__(self, cluster: UpdateCluster, workers: int, resize: Callable[[int], None]) -> None:
        self.cluster = cluster
        self.workers = workers
        self.resize = resize
        self.warm_processes = 0
        self.ready = False

    @property
    def slots(self) -> int:
        return max(1, self.workers)

    def start(self, spawn: Spawn) -> None:
        spawn(self._watch(spawn))

    async def stop(self) -> None:
        return None

    async def run(
        self, payload: dict[str, Any], name: str, gate: ProcessGate, session_id: int
    ) -> tuple[dict[str, Any], int, float]:
        """The outcome, how many workers died running it before it came back, and its wall
        time; it holds one of ``gate``'s slots meanwhile."""
        async with gate.holding(session_id):
            started = time.perf_counter()
            outcome, deaths = await self.cluster.run(run_update, payload, name)
            return outcome, deaths, time.perf_counter() - started

    async def measure(self, request: dict[str, Any]) -> UpdateCost:
        cost, _ = await self.cluster.run(measure_updates, request, "learner-update-reference")
        assert isinstance(cost, UpdateCost)
        return cost

    async def _watch(self, spawn: Spawn) -> None:
        """Follow the cluster's workers: as many updates at once as they have threads, and
        the server ready (``/api/health``) once there are workers and every one is warm."""
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
                warming = spawn(self._warm_up())
            self.workers = workers.threads
            self.warm_processes = workers.warm_threads
            self.resize(workers.threads)
            if not self.ready and workers.threads and workers.warm_threads == workers.threads:
                self.ready = True
                log.info(
                    "%d Dask worker thread(s) ready after %.1f s: the server is ready",
                    workers.threads,
                    time.monotonic() - began,
                )
            await asyncio.sleep(CLUSTER_WATCH_SECONDS if self.ready else 0.5)

    async def _warm_up(self) -> None:
        try:
            await asyncio.to_thread(self.cluster.warm_up_workers)
        except asyncio.CancelledError:
            raise
        except Exception:
            log.exception("could not ask the Dask cluster's workers to warm up")


def _deliver(
    result: asyncio.Future[tuple[Future[Any], float]], future: Future[Any], seconds: float
) -> None:
    """On the loop: an update's end to the coroutine awaiting it (unless it went away)."""
    if not result.done():
        result.set_result((future, seconds))
