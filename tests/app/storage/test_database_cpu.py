"""The CPU time of a PostgreSQL server on the study server's machine, which the capacity
counts with the server's own work per update (server.app.storage.database_cpu)."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import create_engine, event, text
from sqlalchemy.engine import make_url
from sqlalchemy.pool import NullPool

from server.app.storage.database_cpu import (
    application_cpu_reader,
    backend_cpu_reader,
    postgres_cpu_reader,
)
from server.app.storage.db import Database
from server.app.updates.capacity import LIVE_MINIMUM
from server.app.updates.queue import ProcessGate
from tests.support.server import BOUND, POSTGRES_URL, run_apart, wait_until

TICKS = os.sysconf("SC_CLK_TCK")


def busy(connection: Any, seconds: float) -> None:
    """The backend of ``connection`` computes for ``seconds`` of wall time."""
    connection.execute(
        text(
            "DO $$ DECLARE until timestamptz := clock_timestamp() + make_interval(secs => "
            f"{seconds}); BEGIN WHILE clock_timestamp() < until LOOP END LOOP; END $$"
        )
    )


def busy_until(connection: Any, read: Callable[[], float], at_least: float) -> float:
    """The backend of ``connection`` computes until ``read()`` reaches ``at_least`` seconds (a
    bounded wait, not a fixed second: on a loaded machine a second of a backend's wall time
    can be little CPU); the reading that reached it."""
    deadline = time.monotonic() + BOUND
    while (reading := read()) < at_least:
        busy(connection, 0.2)
        assert time.monotonic() < deadline, "the backend's CPU time is not counted"
    return reading


@pytest.fixture
def postgres() -> Any:
    engine = create_engine(POSTGRES_URL, poolclass=NullPool)
    yield engine
    engine.dispose()


def test_a_local_postgresql_servers_cpu_time_counts_its_backends_live_and_ended(
    postgres: Any,
) -> None:
    read = postgres_cpu_reader(postgres)
    assert read is not None, "PostgreSQL on 127.0.0.1 runs on this machine"
    before = read()
    deadline = time.monotonic() + BOUND
    # A backend that computes and stays connected (a pooled connection)...
    with postgres.connect() as connection:
        during = busy_until(connection, read, before + 0.5)
    # ... then one that computes and ends: its time stays counted, in the postmaster's
    # ended children's.
    ended = during
    while ended - during < 0.5:
        with postgres.connect() as connection:
            busy(connection, 0.2)
        ended = read()
        assert time.monotonic() < deadline, "the ended backends' CPU time is not counted"
    assert read() >= ended


def test_the_backend_is_found_while_its_connection_is_open(postgres: Any, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """Without a pool the connection closes when the block ends and its backend exits soon
    after: read from /proc after that, it may be gone, and the reader None (seen on a loaded
    machine). The backend's process is read before its connection closes."""
    from server.app.storage import database_cpu

    order: list[str] = []
    event.listen(postgres, "close", lambda *_: order.append("closed"))
    found = database_cpu.backend_cpu_reader

    def reading(backend: int, proc: Path = database_cpu.PROC) -> Any:
        order.append("read")
        return found(backend, proc)

    monkeypatch.setattr(database_cpu, "backend_cpu_reader", reading)
    assert database_cpu.postgres_cpu_reader(postgres) is not None
    assert order == ["read", "closed"]


def named(application: str) -> Any:
    url = make_url(POSTGRES_URL).update_query_dict({"application_name": application})
    return create_engine(url)


def test_an_applications_backends_are_counted_and_no_other_clients() -> None:
    """The scratch study's backends, not those of another client of the same database server
    (a study under way): a second of another backend's work adds nothing, a second of one of
    its own adds at least half a second, and an ended one keeps its time."""
    own, other = named("bam_test_own"), named("bam_test_other")
    try:
        read = application_cpu_reader(own, "bam_test_own")
        assert read is not None, "PostgreSQL on 127.0.0.1 runs on this machine"
        before = read()
        with other.connect() as connection:
            busy(connection, 1.0)
        assert read() - before < 0.1
        with own.connect() as connection:
            read()  # the backend found while it lives
            during = busy_until(connection, read, before + 0.5)
        own.dispose()  # its backends end
        wait_until(lambda: not application_backends("bam_test_own"), "the backends ended")
        # (The read's own connection is the application's too: a new backend, a few ms.)
        assert during <= read() < during + 0.1
    finally:
        own.dispose()
        other.dispose()


def application_backends(application: str) -> list[int]:
    engine = create_engine(POSTGRES_URL, poolclass=NullPool)
    try:
        with engine.connect() as connection:
            query = text("SELECT pid FROM pg_stat_activity WHERE application_name = :a")
            return list(connection.scalars(query, {"a": application}).all())
    finally:
        engine.dispose()


def test_a_sqlite_database_has_no_processes_of_its_own(tmp_path: Path) -> None:
    database = Database.from_url(f"sqlite:///{tmp_path / 'study.db'}")
    assert postgres_cpu_reader(database.engine) is None
    assert application_cpu_reader(database.engine, "any") is None
    database.dispose()


def write_process(proc: Path, pid: int, name: str, parent: int, times: tuple[int, ...]) -> None:
    folder = proc / str(pid)
    (folder / "task" / str(pid)).mkdir(parents=True, exist_ok=True)
    (folder / "comm").write_text(f"{name}\n")
    # pid (name) state ppid pgrp session tty tpgid flags minflt cminflt majflt cmajflt utime
    # stime cutime cstime ... (a name with spaces and parentheses, as proc(5) allows)
    fields = ["S", str(parent), *["0"] * 9, *map(str, times), "20", "0"]
    (folder / "stat").write_text(f"{pid} ({name}) {' '.join(fields)}\n")


def set_children(proc: Path, pid: int, children: list[int]) -> None:
    (proc / str(pid) / "task" / str(pid) / "children").write_text(
        "".join(f"{child} " for child in children)
    )


def test_the_time_is_the_postmasters_own_its_ended_childrens_and_its_live_childrens(
    tmp_path: Path,
) -> None:
    proc = tmp_path / "proc"
    write_process(proc, 10, "postgres", 1, (100, 50, 400, 30))
    write_process(proc, 11, "postgres", 10, (7, 3, 0, 0))  # the backend asked
    write_process(proc, 12, "postgres", 10, (20, 20, 5, 5))  # its writer
    set_children(proc, 10, [11, 12])
    read = backend_cpu_reader(11, proc)
    assert read is not None
    # own 150, ended children 430, live children 10 + 40 (not their own ended children's)
    assert read() == pytest.approx((150 + 430 + 10 + 40) / TICKS)
    # The backend ends: its ticks move into the postmaster's ended children's...
    write_process(proc, 10, "postgres", 1, (100, 50, 410, 30))
    set_children(proc, 10, [12])
    assert read() == pytest.approx((150 + 440 + 40) / TICKS)
    # ... and read between the two (listed, but gone), the total does not go back.
    set_children(proc, 10, [11, 12])
    write_process(proc, 10, "postgres", 1, (100, 50, 400, 30))
    (proc / "11" / "stat").unlink()
    assert read() == pytest.approx((150 + 440 + 40) / TICKS)


def test_no_reader_where_the_backend_is_not_this_machines_postgres(tmp_path: Path) -> None:
    proc = tmp_path / "proc"
    # The pid a database in a container of its own answers: another process here, or none.
    write_process(proc, 20, "python3", 1, (1, 1, 0, 0))
    assert backend_cpu_reader(20, proc) is None
    assert backend_cpu_reader(21, proc) is None
    # A postgres process whose parent is not the postmaster (or lists no children).
    write_process(proc, 30, "postgres", 29, (1, 1, 0, 0))
    write_process(proc, 29, "bash", 1, (1, 1, 0, 0))
    set_children(proc, 29, [30])
    assert backend_cpu_reader(30, proc) is None
    write_process(proc, 40, "postgres", 41, (1, 1, 0, 0))
    write_process(proc, 41, "postgres", 1, (1, 1, 0, 0))
    assert backend_cpu_reader(40, proc) is None


class Instant:
    """A runner of one slot whose updates end at once, 0.05 s of wall time each (and, with
    ``cpu``, that much of their process's CPU time)."""

    slots = 1

    def __init__(self, cpu: float | None = None) -> None:
        self.outcome = {} if cpu is None else {"cpu_seconds": cpu}

    async def run(self, payload: Any, name: str, gate: Any, session_id: int) -> Any:
        return self.outcome, 0, 0.05


def run_live_updates(manager: Any) -> float:
    """``LIVE_MINIMUM + 1`` updates through the manager's ``_run``; this process's CPU time
    meanwhile."""
    from server.app.updates.store import Job

    manager._processes = ProcessGate(1, lambda session_id: (0, 0.0))
    job = Job(update_id=1, session_id=1, update_index=1, environment="wall", payload={})

    async def run_updates() -> float:
        started = time.process_time()
        for _ in range(LIVE_MINIMUM + 1):
            await manager._run(job)
        return time.process_time() - started

    return float(run_apart(run_updates))


def test_the_live_capacity_adds_the_databases_cpu_time_to_the_servers(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from server.app.updates import manager as manager_module
    from server.app.updates.manager import UpdateManager
    from server.app.updates.policies import PolicyCache

    monkeypatch.setattr(manager_module, "available_cores", lambda: 1)
    database = [0.0]

    def database_cpu() -> float:
        database[0] += 0.25  # the database's work during each update
        return database[0]

    db: Database = None  # type: ignore[assignment]
    manager = UpdateManager(
        db, PolicyCache(), lambda name: {}, workers=1, database_cpu=database_cpu
    )
    manager.runner = Instant()  # type: ignore[assignment]
    own = run_live_updates(manager)
    capacity = manager.capacity()
    assert capacity is not None and capacity.update_seconds == pytest.approx(0.05)
    # The database's 0.25 s an update, and this process's own (a share of what it spent).
    assert capacity.server_seconds is not None
    assert 0.25 <= capacity.server_seconds <= 0.25 + own / LIVE_MINIMUM


@pytest.mark.parametrize("on_a_cluster", [False, True])
def test_a_live_updates_cost_is_its_cpu_time_where_it_shares_the_servers_cores(
    on_a_cluster: bool,
) -> None:
    """Under load an update's wall time counts the moments the server's work held its core,
    which the capacity counts apart; on a cluster's cores of their own, its wall time."""
    from server.app.updates.manager import UpdateManager
    from server.app.updates.policies import PolicyCache

    db: Database = None  # type: ignore[assignment]
    manager = UpdateManager(db, PolicyCache(), lambda name: {}, workers=1)
    manager.runner = Instant(cpu=0.02)  # type: ignore[assignment]
    if on_a_cluster:
        manager.cluster = object()  # type: ignore[assignment]
    run_live_updates(manager)
    capacity = manager.capacity()
    assert capacity is not None
    assert capacity.update_seconds == pytest.approx(0.05 if on_a_cluster else 0.02)
