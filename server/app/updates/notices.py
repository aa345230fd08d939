"""What the servers of a deployment tell each other about the learner updates, over
PostgreSQL's ``LISTEN``/``NOTIFY``: an update stored (the session's waiters on every server go
on), a session with new pending updates (any server with a free slot may claim it), and an
agent someone began to wait for (every server's queue puts the session first).

A notice is sent inside the transaction that makes it true (``UpdateStore``), or in one of its
own, and delivered when that commits. Each server listens in a thread of its own, on a
connection of its own, and hands the notices to its queue on the event loop. A notice missed
(the connection dropped for a moment) costs time, not correctness: a waiter also looks in the
database every ``DB_POLL_SECONDS``, and the rescan finds pending updates nobody holds.

The channel is named after the database and schema, so studies that share a PostgreSQL server
(or the tests' schemas) do not hear each other.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import logging
import threading
from collections.abc import Callable
from typing import Any

from sqlalchemy import Engine, text

log = logging.getLogger("bam_study.updates")

RECONNECT_SECONDS = 1.0


def channel_of(engine: Engine) -> str:
    """The deployment's channel: one per database and schema."""
    with engine.connect() as connection:
        database, schema = connection.execute(
            text("SELECT current_database(), current_schema()")
        ).one()
    digest = hashlib.sha256(f"{database}\0{schema}".encode()).hexdigest()[:20]
    return f"bam_updates_{digest}"


def conninfo_of(engine: Engine) -> str:
    """The engine's database as a libpq URI (its search path too), for psycopg itself."""
    url = engine.url.set(drivername="postgresql")
    return url.render_as_string(hide_password=False)


class Listener:
    """``LISTEN`` on the channel in a thread; each notice from another server (not this one:
    ``server``) is handed to ``handle`` on ``loop``."""

    def __init__(
        self,
        engine: Engine,
        channel: str,
        server: str,
        handle: Callable[[dict[str, Any]], None],
    ) -> None:
        self.conninfo = conninfo_of(engine)
        self.channel = channel
        self.server = server
        self.handle = handle
        self.listening = threading.Event()  # set while the connection listens
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._thread = threading.Thread(target=self._listen, name="update-notices", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)

    def _listen(self) -> None:
        import psycopg
        from psycopg import sql

        while not self._stop.is_set():
            try:
                with psycopg.connect(self.conninfo, autocommit=True) as connection:
                    connection.execute(sql.SQL("LISTEN {}").format(sql.Identifier(self.channel)))
                    self.listening.set()
                    while not self._stop.is_set():
                        for notice in connection.notifies(timeout=0.5):
                            self._hand(notice.payload)
            except Exception as error:  # the database went away: listen again in a moment
                log.warning("update notices interrupted (%s); listening again", error)
            finally:
                self.listening.clear()
            self._stop.wait(RECONNECT_SECONDS)

    def _hand(self, payload: str) -> None:
        try:
            notice = json.loads(payload)
        except ValueError:
            return
        if not isinstance(notice, dict) or notice.get("from") == self.server:
            return
        assert self._loop is not None
        try:
            self._loop.call_soon_threadsafe(self.handle, notice)
        except RuntimeError:  # the loop closed: the server stops
            self._stop.set()
