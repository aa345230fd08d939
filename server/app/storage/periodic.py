"""Jobs that one server of a deployment runs at a time: the periodic ones (time-outs,
scrubbing expired platform ids), once per period between all the servers, and the capacity's
timing at start, one server after another (servers on one machine timing side by side would
each find the others' updates in their way).

On PostgreSQL an advisory lock says which server runs a job now, and ``periodic_runs`` when it
last ran. SQLite has one server (a second is refused at start): it runs them itself.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from datetime import timedelta

from sqlalchemy import func, select

from server.app.storage.db import Database, advisory_lock_key
from server.app.storage.models import PeriodicRun, utcnow

LOCK_POLL_SECONDS = 1.0


def once_per_period(
    db: Database, job: str, seconds: float, server: str, work: Callable[[], None]
) -> bool:
    """Run ``work`` unless another server runs ``job`` now or ran it within the last
    ``seconds`` (a little less: servers' timers drift); whether it ran here. Blocking."""
    if db.is_sqlite:
        work()
        return True
    key = advisory_lock_key(f"bam-study periodic {job}")
    with db.write() as s:
        # Held until this transaction ends, after the work and its record.
        if not s.scalar(select(func.pg_try_advisory_xact_lock(key))):
            return False
        last = s.get(PeriodicRun, job)
        if last is not None and last.ran_at > utcnow() - timedelta(seconds=0.9 * seconds):
            return False
        work()
        if last is None:
            s.add(PeriodicRun(job=job, ran_at=utcnow(), ran_by=server))
        else:
            last.ran_at, last.ran_by = utcnow(), server
    return True


@asynccontextmanager
async def one_server_at_a_time(db: Database | None, job: str) -> AsyncIterator[None]:
    """``async with``: the block runs on one server of the deployment at a time (PostgreSQL:
    a session's advisory lock on a connection held meanwhile; SQLite, or no database: one
    server anyway)."""
    if db is None or db.is_sqlite:
        yield
        return
    key = advisory_lock_key(f"bam-study one at a time {job}")
    connection = await asyncio.to_thread(db.engine.connect)
    try:

        def locked() -> bool:
            got = bool(connection.scalar(select(func.pg_try_advisory_lock(key))))
            connection.commit()
            return got

        while not await asyncio.to_thread(locked):
            await asyncio.sleep(LOCK_POLL_SECONDS)
        try:
            yield
        finally:
            await asyncio.to_thread(
                lambda: connection.execute(select(func.pg_advisory_unlock(key)))
            )
            await asyncio.to_thread(connection.commit)
    finally:
        await asyncio.to_thread(connection.close)
