"""The CPU time of a PostgreSQL server that runs on the study server's own machine.

Such a database takes its share of the cores the update processes have: each request's
statements run in a backend process of its own, and its writers and checkpointer run beside
them (up to half a core of two at 200 participants, docs/benchmarks.md). The capacity counts
that share with the server's own work per update (``server.app.updates.capacity``).

Read from Linux's ``/proc``: the postmaster is the parent of the backend that answers
``pg_backend_pid()``; its CPU time so far is its own, its ended children's (``cutime`` and
``cstime``: a backend whose connection closed is counted there once reaped) and its live
children's (listed in ``/proc/<pid>/task/<pid>/children``). Every client's backends are counted:
on a study server's machine the database's work is the study's. ``application_cpu_reader``
counts those of one application's connections only (the scratch study that times the server's
own work at start, ``server.commands.server_share``). Where the database runs on
another machine, or in a container of its own (its process ids are not this machine's), or
``/proc`` lacks what is read, there is nothing to count here and the reader is None. SQLite runs
in the server's own process, whose CPU time the capacity counts already.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

from sqlalchemy import Engine, text

PROC = Path("/proc")
POSTGRES = "postgres"  # the name of the postmaster's and its backends' processes


def postgres_cpu_reader(engine: Engine, proc: Path = PROC) -> Callable[[], float] | None:
    """A function giving the CPU seconds that the PostgreSQL server behind ``engine`` has used
    so far, if it runs on this machine (the module docstring); else None."""
    if engine.dialect.name != "postgresql":
        return None
    try:
        with engine.connect() as connection:
            backend = int(connection.scalar(text("SELECT pg_backend_pid()")) or 0)
            # Found while the connection is open: once closed (an engine without a pool, or a
            # pool that drops it), its backend may exit before ``proc`` is read.
            return backend_cpu_reader(backend, proc)
    except Exception:
        return None


def backend_cpu_reader(backend: int, proc: Path = PROC) -> Callable[[], float] | None:
    """``postgres_cpu_reader`` of the server whose backend process is ``backend``, as this
    machine's ``proc`` shows it: None where no postmaster named ``postgres`` is its parent."""
    backend_stat = _stat(proc, backend)
    if backend_stat is None or _name(proc, backend) != POSTGRES:
        return None
    postmaster = int(backend_stat[1])
    if _name(proc, postmaster) != POSTGRES or _children(proc, postmaster) is None:
        return None
    ticks = float(os.sysconf("SC_CLK_TCK"))
    last = [0.0]

    def read() -> float:
        stat = _stat(proc, postmaster)
        children = _children(proc, postmaster)
        if stat is None or children is None:
            return last[0]  # the database stopped: no more of its work to count
        total = sum(int(field) for field in stat[11:15])  # utime, stime, cutime, cstime
        for child in children:
            child_stat = _stat(proc, child)
            if child_stat is not None:  # (else it ended meanwhile)
                total += _own_ticks(child_stat)
        # A child that ended between the two reads moves from one sum to the other: never
        # let the total go back.
        last[0] = max(last[0], total / ticks)
        return last[0]

    return read


def application_cpu_reader(
    engine: Engine, application: str, proc: Path = PROC
) -> Callable[[], float] | None:
    """A function giving the CPU seconds that the backends of the connections named
    ``application`` (their ``application_name``) have used so far, on a PostgreSQL server on
    this machine; None where ``postgres_cpu_reader`` finds none. Other clients' backends are not
    counted (a study already under way on the same database server, say), nor the server's
    writers. A backend is counted from the first read that finds it, with the time it has used
    since it started; one that ended keeps the time last read."""
    if postgres_cpu_reader(engine, proc) is None:
        return None
    ticks = float(os.sysconf("SC_CLK_TCK"))
    used: dict[int, float] = {}  # a backend's CPU seconds at the last read that found it
    backends = text("SELECT pid FROM pg_stat_activity WHERE application_name = :application")

    def read() -> float:
        with engine.connect() as connection:
            found = connection.scalars(backends, {"application": application}).all()
        for pid in found:
            stat = _stat(proc, int(pid))
            if stat is not None:  # (else it ended meanwhile)
                seconds = _own_ticks(stat) / ticks
                used[int(pid)] = max(used.get(int(pid), 0.0), seconds)
        return sum(used.values())

    return read


def _own_ticks(stat: list[str]) -> int:
    """A process's own CPU time in clock ticks (``utime`` and ``stime`` of ``_stat``'s fields)."""
    return int(stat[11]) + int(stat[12])


def _stat(proc: Path, pid: int) -> list[str] | None:
    """The fields of ``/proc/<pid>/stat`` after the process's name (state, ppid, ...: field 3
    of proc(5) is index 0), or None where there is no such process."""
    try:
        line = (proc / str(pid) / "stat").read_text()
    except (OSError, ValueError):
        return None
    return line[line.rindex(")") + 2 :].split()


def _name(proc: Path, pid: int) -> str | None:
    try:
        return (proc / str(pid) / "comm").read_text().strip()
    except OSError:
        return None


def _children(proc: Path, pid: int) -> list[int] | None:
    try:
        listed = (proc / str(pid) / "task" / str(pid) / "children").read_text()
    except OSError:
        return None
    return [int(child) for child in listed.split()]
