"""The live views' reads in a process of their own (``BAM_LIVE_READER=process``, the default):
while dashboards stay open, the funnel, the curves and each watched participant's mirror are
read from the database there, and the server only passes on what comes back. On SQLite the
server runs its transactions in its event loop, so a read of the live views there delayed every
participant's request behind it; in a process of its own, at the update processes' lower
priority, it runs beside the server on another core. The process starts when the first view is
watched and stops with the server; one that dies is started again at the next read.

With ``BAM_LIVE_READER=server`` the reads run in the server's process (``ServerState.run_db``):
on a one-core machine there is no other core to read on.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from datetime import datetime
from typing import Any

from server.app.live import curves, funnel, mirror
from server.app.storage.db import Database
from server.app.study_file import StudyConfig
from server.app.updates.worker import serve_the_server
from server.domains import register_all, registered
from server.domains.spec import EnvironmentSpec

log = logging.getLogger("bam_study")

UNCHANGED = "unchanged"  # a mirror read: the participant's view is as it was

# The reading process's own: set by ``_start`` there.
_db: Database | None = None
_study: StudyConfig | None = None


def _start(
    database_url: str,
    study: StudyConfig,
    environments: tuple[EnvironmentSpec, ...],
    niceness: int,
    server_pid: int,
) -> None:
    """The reading process's initialiser: the study's environments known, the update
    processes' priority, and gone with the server (a killed server leaves no reader behind)."""
    global _db, _study
    serve_the_server(niceness, server_pid)
    register_all(environments)
    _db, _study = Database.from_url(database_url), study


def _database() -> Database:
    assert _db is not None, "the reader's initialiser sets the database"
    return _db


def read_funnel(now: datetime) -> dict[str, Any]:
    with _database().connect() as c:
        return funnel.funnel(c, now)


def read_curves() -> dict[str, Any]:
    with _database().connect() as c:
        return curves.live_curves(c)


def read_mirror(participant_id: int, seen: Any) -> tuple[Any, Any]:
    """The participant's fingerprint and, when it is not ``seen``, their view (else
    ``UNCHANGED``): the question and the answer in one transaction and one round trip."""
    assert _study is not None
    with _database().connect() as c:
        now = mirror.fingerprint(c, participant_id)
        if now == seen:
            return now, UNCHANGED
        return now, mirror.mirror_view(c, _study, participant_id)


class LiveReader:
    """One process that reads the live views for the server, started at the first read."""

    def __init__(self, database_url: str, study: StudyConfig, niceness: int) -> None:
        self.database_url, self.study, self.niceness = database_url, study, niceness
        self._pool: ProcessPoolExecutor | None = None

    def _executor(self) -> ProcessPoolExecutor:
        if self._pool is None:
            # Spawned, not forked: the server process has threads.
            self._pool = ProcessPoolExecutor(
                max_workers=1,
                mp_context=multiprocessing.get_context("spawn"),
                initializer=_start,
                initargs=(
                    self.database_url,
                    self.study,
                    registered(),
                    self.niceness,
                    os.getpid(),
                ),
            )
        return self._pool

    async def run(self, read: Any, *args: Any) -> Any:
        """``read(*args)`` in the reading process; a reader that died is replaced (once)."""
        loop = asyncio.get_running_loop()
        try:
            return await loop.run_in_executor(self._executor(), read, *args)
        except BrokenProcessPool:
            log.warning("the live views' reader died; starting another")
            self._drop()
            return await loop.run_in_executor(self._executor(), read, *args)

    def _drop(self) -> None:
        pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)

    @property
    def pid(self) -> int | None:
        """The reading process's id, once it runs (for the tests)."""
        processes = getattr(self._pool, "_processes", None) or {}
        return next(iter(processes), None)

    async def stop(self) -> None:
        pool, self._pool = self._pool, None
        if pool is not None:
            await asyncio.to_thread(pool.shutdown, True, cancel_futures=True)
