"""The servers of a deployment, as the database knows them: each ``bam-study serve`` process
has a row in ``servers`` with its name (the one its claims on learner updates carry), where it
runs, and a heartbeat with its load, written every ``heartbeat_seconds`` (a third of the
update lease, so a server whose heartbeat is older than its lease is gone: its claims are
taken over). The dashboard lists them; the deployment's capacity is the sum of theirs.
"""

from __future__ import annotations

import os
import secrets
import socket
from dataclasses import dataclass
from datetime import datetime, timedelta

from sqlalchemy import select

from server.app.storage.db import Database
from server.app.storage.models import StudyServer, utcnow


def server_name() -> str:
    """A name no other server of the deployment has: host, process id and a random suffix
    (a restarted container may get the same process id)."""
    host = socket.gethostname()[:40] or "host"
    return f"{host}-{os.getpid()}-{secrets.token_hex(3)}"


@dataclass(frozen=True)
class ServerLoad:
    """What a server's heartbeat says of it."""

    update_slots: int
    updates_running: int
    updates_completed: int
    updates_failed: int
    participants_at_once: int | None


@dataclass(frozen=True)
class ServerView:
    """A server as the dashboard shows it: ``live`` while its heartbeat is recent."""

    name: str
    host: str
    pid: int
    started_at: datetime
    heartbeat_at: datetime
    stopped_at: datetime | None
    live: bool
    load: ServerLoad


class ServerRegistry:
    """This server's row in ``servers``."""

    def __init__(self, db: Database, name: str) -> None:
        self.db = db
        self.name = name

    def register(self, load: ServerLoad) -> None:
        now = utcnow()
        with self.db.write() as s:
            s.add(
                StudyServer(
                    name=self.name,
                    host=socket.gethostname()[:255],
                    pid=os.getpid(),
                    started_at=now,
                    heartbeat_at=now,
                    **vars(load),
                )
            )

    def beat(self, load: ServerLoad) -> None:
        with self.db.write() as s:
            row = s.get(StudyServer, self.name)
            if row is None:  # removed by hand: this server is back
                s.add(StudyServer(name=self.name, host=socket.gethostname()[:255], pid=os.getpid()))
                s.flush()
                row = s.get(StudyServer, self.name)
                assert row is not None
            row.heartbeat_at = utcnow()
            row.stopped_at = None
            for name, value in vars(load).items():
                setattr(row, name, value)

    def stopped(self) -> None:
        with self.db.write() as s:
            row = s.get(StudyServer, self.name)
            if row is not None:
                row.stopped_at = utcnow()
                row.updates_running = 0


def deployment_servers(db: Database, gone_after_seconds: float) -> list[ServerView]:
    """Every server that has run on the database, the latest started first; ``live`` where it
    has not stopped and beat within ``gone_after_seconds``."""
    now = utcnow()
    with db.read() as s:
        rows = list(s.scalars(select(StudyServer).order_by(StudyServer.started_at.desc())))
    return [
        ServerView(
            name=row.name,
            host=row.host,
            pid=row.pid,
            started_at=row.started_at,
            heartbeat_at=row.heartbeat_at,
            stopped_at=row.stopped_at,
            live=row.stopped_at is None
            and row.heartbeat_at > now - timedelta(seconds=gone_after_seconds),
            load=ServerLoad(
                update_slots=row.update_slots,
                updates_running=row.updates_running,
                updates_completed=row.updates_completed,
                updates_failed=row.updates_failed,
                participants_at_once=row.participants_at_once,
            ),
        )
        for row in rows
    ]


def others_load(db: Database, name: str, gone_after_seconds: float) -> tuple[int, int]:
    """The participants at once and the update slots of the deployment's other live servers
    (those that stated a capacity), from their heartbeats."""
    participants = slots = 0
    for server in deployment_servers(db, gone_after_seconds):
        if server.live and server.name != name:
            participants += server.load.participants_at_once or 0
            slots += server.load.update_slots
    return participants, slots
