"""The servers of a deployment, as the database knows them: each ``bam-study serve`` process
has a row in ``servers`` with its name (the one its claims on learner updates carry), where it
runs, and a heartbeat with its load, written every ``heartbeat_seconds`` (a third of the
update lease, so a server whose heartbeat is older than its lease is gone: its claims are
taken over). The dashboard lists them; the deployment's capacity is summed from theirs, each
machine's cores once (``capacity.deployment_participants``): a heartbeat says where the
server's update slots run (``slots_machine``) and the costs its capacity was stated from.
"""

from __future__ import annotations

import os
import secrets
import socket
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path

from sqlalchemy import select

from server.app.storage.db import Database
from server.app.storage.models import StudyServer, utcnow
from server.app.updates.capacity import ServerSlots

BOOT_ID = Path("/proc/sys/kernel/random/boot_id")
LOOPBACK = ("127.", "localhost", "[::1]")


def server_name() -> str:
    """A name no other server of the deployment has: host, process id and a random suffix
    (a restarted container may get the same process id)."""
    host = socket.gethostname()[:40] or "host"
    return f"{host}-{os.getpid()}-{secrets.token_hex(3)}"


def this_machine() -> str:
    """Which cores this process's update processes share: the kernel's boot id (one a machine,
    shared by its containers, unlike their host names) and the cores this process may run on
    (containers given cores of their own share none). The host name where there is no boot id
    (not Linux)."""
    try:
        kernel = BOOT_ID.read_text().strip()
    except OSError:
        kernel = ""
    try:
        allowed = sorted(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        allowed = []
    cores = ",".join(map(str, allowed))
    return f"{kernel or socket.gethostname()} cores {cores or os.cpu_count()}"[:255]


def slots_machine(cluster_address: str | None) -> str:
    """Where a server's update slots run: this machine's cores, or the Dask cluster's workers
    (its scheduler's address; one on a loopback address is this machine's own)."""
    if cluster_address is None:
        return this_machine()
    if any(part in cluster_address for part in LOOPBACK):
        return f"dask {cluster_address} on {this_machine()}"[:255]
    return f"dask {cluster_address}"[:255]


@dataclass(frozen=True)
class ServerLoad:
    """What a server's heartbeat says of it: its load, and what the deployment's capacity is
    summed from (``ServerSlots``)."""

    update_slots: int
    updates_running: int
    updates_completed: int
    updates_failed: int
    participants_at_once: int | None
    machine: str = ""  # where its update slots run (``slots_machine``)
    cores: int | None = None  # the cores they share with the server (None: a cluster's)
    update_seconds: float | None = None  # the update cost its capacity is from (None: untimed)
    server_seconds: float | None = None  # the server's own work per update (None: not counted)


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
                machine=row.machine,
                cores=row.cores,
                update_seconds=row.update_seconds,
                server_seconds=row.server_seconds,
            ),
        )
        for row in rows
    ]


def others_slots(db: Database, name: str, gone_after_seconds: float) -> list[ServerSlots]:
    """The update slots of the deployment's other live servers that stated a capacity, from
    their heartbeats."""
    return [
        ServerSlots(
            machine=server.load.machine,
            slots=server.load.update_slots,
            cores=server.load.cores,
            update_seconds=server.load.update_seconds,
            server_seconds=server.load.server_seconds,
        )
        for server in deployment_servers(db, gone_after_seconds)
        if server.live and server.name != name and server.load.update_seconds is not None
    ]
