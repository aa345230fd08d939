"""The order of the learner updates, and the waits for them (see ``server.app.updates.manager``
for the whole): which session's update runs next, and who waits for which update.

Every method but ``submit`` and ``expect`` (which hop onto it) runs on the event loop the queue
was started on; ``wait`` may be awaited from any loop. Order changes only between sessions: a
session is taken once, its next update runs, and it comes back to the queue when it has more.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass

# A waiting agent step is woken at once by an update this process commits; it looks in the
# database this often for one another process committed (a thread hop and a query each: at
# 200 participants, once a second per waiter was a measurable share of the server's CPU).
DB_POLL_SECONDS = 5.0


@dataclass(frozen=True)
class QueueState:
    sessions_queued: int  # sessions with updates pending, waiting for a slot
    sessions_updating: int  # sessions with an update running
    sessions_awaited: int  # of those, sessions someone waits for
    oldest_wait_seconds: float  # how long the longest of those waits has lasted
    slots: int  # updates that run at once
    completed: int  # updates done since the server started
    failed: int


class Claim:
    """A prepared update's claim on a process: ``begin`` is called once one is its."""

    __slots__ = ("begin",)

    def __init__(self, begin: Callable[[], None]) -> None:
        self.begin = begin


class ProcessGate:
    """The update processes (or cluster slots), handed out by urgency: when one frees, the
    prepared update whose session is awaited longest takes it, else the one prepared first.
    ``priority`` is read at that moment, so an update read from the database before anyone
    waited for it goes first once someone does (a FIFO semaphore left it behind the updates
    prepared before it).

    Thread-safe: whichever thread frees a process hands it on. A local update's end is seen in
    the process pool's own thread, which starts the next prepared update there and then, so
    that an update process never waits for a turn of the server's event loop (busy with
    participants' requests, a turn took 60 ms at the median and 250 ms at p95 with 200
    simulated participants on an Intel Xeon, 2 cores, and the update processes idled 60% of
    the time between updates)."""

    def __init__(self, processes: int, priority: Callable[[int], tuple[int, float]]) -> None:
        self.free = processes  # below 0 while more are held than there are (after a shrink)
        self.priority = priority
        self._lock = threading.Lock()
        self._waiting: dict[Claim, int] = {}  # in the order they came

    @property
    def waiting(self) -> int:
        return len(self._waiting)

    def claim(self, session_id: int, begin: Callable[[], None]) -> Claim:
        """``begin()`` once a process is the session's prepared update's: at once in this
        thread if one is free and no other waits, else in the thread that frees one. ``begin``
        must not raise, and the process is held until ``release``."""
        claim = Claim(begin)
        with self._lock:
            now = self.free > 0 and not self._waiting
            if now:
                self.free -= 1
            else:
                self._waiting[claim] = session_id
        if now:
            begin()
        return claim

    def withdraw(self, claim: Claim) -> bool:
        """Take back a claim not yet handed a process (True); False: it has been handed one."""
        with self._lock:
            return self._waiting.pop(claim, None) is not None

    async def acquire(self, session_id: int) -> None:
        """A process for the session's prepared update, on the running event loop (waits)."""
        loop = asyncio.get_running_loop()
        future: asyncio.Future[None] = loop.create_future()
        claim = self.claim(session_id, lambda: _hand_over(loop, future, self))
        try:
            await future
        except asyncio.CancelledError:
            # Handed a process already: the holder passes it on (``_hand_over`` does when
            # the future is cancelled before it ran).
            if not self.withdraw(claim) and future.done() and not future.cancelled():
                self.release()
            raise

    def release(self) -> None:
        with self._lock:
            self.free += 1
        self._hand_out()

    def resize(self, change: int) -> None:
        """``change`` processes more (or fewer: the next ones released are not handed out)."""
        with self._lock:
            self.free += change
        self._hand_out()

    def _hand_out(self) -> None:
        while True:
            with self._lock:
                if self.free <= 0 or not self._waiting:
                    return
                # min keeps the first of equals: the order they came in.
                claim = min(self._waiting, key=lambda c: self.priority(self._waiting[c]))
                del self._waiting[claim]
                self.free -= 1
            claim.begin()  # outside the lock: it starts an update, or hops to a loop

    @asynccontextmanager
    async def holding(self, session_id: int) -> AsyncIterator[None]:
        """``async with gate.holding(session_id):`` a process while the block runs."""
        await self.acquire(session_id)
        try:
            yield
        finally:
            self.release()


def _hand_over(
    loop: asyncio.AbstractEventLoop, future: asyncio.Future[None], gate: ProcessGate
) -> None:
    """A process for ``acquire``'s waiter, from any thread."""

    def handed() -> None:
        if future.cancelled():  # its waiter went away: pass the process on
            gate.release()
        else:
            future.set_result(None)

    try:
        loop.call_soon_threadsafe(handed)
    except RuntimeError:  # the loop is closed: the server stopped
        gate.release()


class UpdateQueue:
    """Sessions with pending updates, in dispatch order: awaited sessions first, the one
    awaited longest first, then the others in the order their updates were queued."""

    def __init__(
        self,
        processed_in_db: Callable[[int], int],
        share_awaited: Callable[[int, int, float], None] | None = None,
    ) -> None:
        # The session's latest processed update as the database has it (a blocking call, run
        # in a thread): another server process may have done it.
        self.processed_in_db = processed_in_db
        # Told (on the loop) of a wait that began here, with the session, the update awaited
        # and since when (seconds since the epoch): the deployment's other servers put the
        # session first too (``UpdateManager``; None: one server).
        self.share_awaited = share_awaited
        self.loop: asyncio.AbstractEventLoop | None = None
        self._wake: asyncio.Event | None = None
        self._ready: dict[int, int] = {}  # session -> turn
        self._turn = 0
        self._running: set[int] = set()
        self._again: set[int] = set()
        # session -> (when someone began waiting, the update index they wait for)
        self._awaited: dict[int, tuple[float, int]] = {}
        self._processed: dict[int, int] = {}
        self._waiters: dict[int, list[asyncio.Future[None]]] = {}

    def start(self) -> None:
        """Bind the queue to the running event loop."""
        self.loop = asyncio.get_running_loop()
        self._wake = asyncio.Event()

    def stop(self) -> None:
        """Cancel every wait (the waiters see the server stop)."""
        for futures in self._waiters.values():
            for future in futures:
                future.cancel()

    # -- queueing ----------------------------------------------------------------------------
    def submit(self, session_ids: list[int]) -> None:
        """Thread-safe: these sessions have new pending updates."""
        if not session_ids or self.loop is None:
            return
        self.loop.call_soon_threadsafe(self.enqueue_many, list(session_ids))

    def enqueue_many(self, session_ids: list[int]) -> None:
        for session_id in session_ids:
            self.enqueue(session_id)

    def enqueue(self, session_id: int) -> None:
        if session_id in self._running:
            self._again.add(session_id)
            return
        if session_id not in self._ready:
            self._turn += 1
            self._ready[session_id] = self._turn
        assert self._wake is not None
        self._wake.set()

    @property
    def queued(self) -> int:
        """Sessions waiting for a slot (read from any thread: the process pool's hands out
        planner threads by it)."""
        return len(self._ready)

    @property
    def updating(self) -> int:
        """Sessions being updated here."""
        return len(self._running)

    @property
    def backlog(self) -> int:
        """Sessions waiting for a slot or being updated."""
        return len(self._ready) + len(self._running)

    def priority(self, session_id: int) -> tuple[int, float]:
        """The dispatch order (smallest first): awaited sessions by how long they have been
        awaited, then the others by when their updates were queued."""
        awaited = self._awaited.get(session_id)
        if awaited is not None:
            return (0, awaited[0])
        return (1, float(self._ready.get(session_id, 0)))

    async def take(self) -> int:
        """The next session to update (waits for one), marked running."""
        assert self._wake is not None
        while not self._ready:
            self._wake.clear()
            await self._wake.wait()
        session_id = min(self._ready, key=self.priority)
        del self._ready[session_id]
        self._running.add(session_id)
        return session_id

    def finish(self, session_id: int, more: bool) -> None:
        """The session's update ended (``more``: it has further updates pending)."""
        self._running.discard(session_id)
        if more or session_id in self._again:
            self._again.discard(session_id)
            self.enqueue(session_id)
        else:  # nothing left to wait for (a mark from a race, or updates that failed)
            self._awaited.pop(session_id, None)

    def retry_later(self, session_id: int, seconds: float) -> None:
        assert self.loop is not None
        self.loop.call_later(seconds, self.enqueue, session_id)

    # -- waiting -----------------------------------------------------------------------------
    def expect(self, session_id: int, target: int) -> None:
        """Thread-safe: the session's agent's turn is next (the participant let it try) and its
        update ``target`` is pending: someone waits for it from now on."""
        if self.loop is None:
            return
        self.loop.call_soon_threadsafe(self.mark_awaited, session_id, target)

    def mark_awaited(self, session_id: int, target: int, since_epoch: float | None = None) -> None:
        """Someone waits for the session's update ``target``: from now, or, told by another
        server, from ``since_epoch`` (seconds since the epoch)."""
        assert self.loop is not None
        if self._processed.get(session_id, -1) >= target:
            return
        now = self.loop.time()
        since = now if since_epoch is None else now - max(0.0, time.time() - since_epoch)
        known = self._awaited.get(session_id)
        if known is None:
            self._awaited[session_id] = (since, target)
        else:
            self._awaited[session_id] = (min(known[0], since), max(known[1], target))
        if since_epoch is None and self.share_awaited is not None:
            if known is None or target > known[1]:
                first = self._awaited[session_id][0]
                self.share_awaited(session_id, target, time.time() - (now - first))
        self.enqueue(session_id)

    async def wait(
        self, session_id: int, target: int, timeout: float, awaited: bool = True
    ) -> bool:
        """Wait until the session's update ``target`` is processed; False on timeout. With
        ``awaited`` (an agent step, or the page in agent mode) someone waits for it: the
        session goes first until it is done, also after this wait times out (the waiter
        retries). Callable from any event loop (the queue's state lives on its own)."""
        assert self.loop is not None
        if asyncio.get_running_loop() is not self.loop:
            waiting = asyncio.run_coroutine_threadsafe(
                self._wait(session_id, target, timeout, awaited), self.loop
            )
            return await asyncio.wrap_future(waiting)
        return await self._wait(session_id, target, timeout, awaited)

    async def _wait(self, session_id: int, target: int, timeout: float, awaited: bool) -> bool:
        assert self.loop is not None
        deadline = self.loop.time() + timeout
        if awaited:
            self.mark_awaited(session_id, target)
        else:
            self.enqueue(session_id)
        while True:
            if self._processed.get(session_id, -1) >= target:
                return True
            remaining = deadline - self.loop.time()
            if remaining <= 0:
                return False
            future: asyncio.Future[None] = self.loop.create_future()
            self._waiters.setdefault(session_id, []).append(future)
            try:
                await asyncio.wait_for(future, min(remaining, DB_POLL_SECONDS))
            except TimeoutError:
                # Also look in the database, in case another process did the update.
                processed = await asyncio.to_thread(self.processed_in_db, session_id)
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

    def notify(self, session_id: int, index: int) -> None:
        """The session's updates up to ``index`` are processed: its waiters go on."""
        self._note_processed(session_id, index)
        for future in self._waiters.get(session_id, []):
            if not future.done():
                future.set_result(None)

    def awaited(self) -> dict[int, tuple[float, int]]:
        """Session -> (when someone began waiting, the update index awaited)."""
        return dict(self._awaited)

    def state(self, slots: int, completed: int, failed: int) -> QueueState:
        """What the dashboard shows of the live queue (call it on the queue's loop, or accept
        a snapshot a moment old)."""
        now = self.loop.time() if self.loop is not None else 0.0
        waits = [now - since for since, _ in list(self._awaited.values())]
        return QueueState(
            sessions_queued=len(self._ready),
            sessions_updating=len(self._running),
            sessions_awaited=len(waits),
            oldest_wait_seconds=max(waits, default=0.0),
            slots=slots,
            completed=completed,
            failed=failed,
        )
