"""What one server of a deployment does at a time: the periodic jobs run once per period
between the servers, not while another runs them (PostgreSQL's advisory locks), the capacity is
timed by one server after another; and a SQLite study has one server: a second on the same
file is refused at start."""

from __future__ import annotations

import asyncio
import threading
from pathlib import Path

import pytest

from server.app.storage.db import Database, SecondServer, SingleServerLock
from server.app.storage.periodic import once_per_period, one_server_at_a_time
from server.commands.main import main
from tests.support.server import ADMIN_TOKEN, BOUND, run_apart


@pytest.mark.parametrize("backend", ["postgresql"])
def test_a_periodic_job_runs_once_per_period_across_the_servers(db: Database) -> None:
    ran: list[str] = []
    for server in ("server-a", "server-b", "server-c"):
        once_per_period(db, "time-outs", 60, server, lambda: ran.append("time-outs"))
    assert ran == ["time-outs"]  # the first server ran it; the others found it done
    # Another job is another period.
    assert once_per_period(db, "scrubbing", 60, "server-b", lambda: ran.append("scrubbing"))
    # While one server runs a job, another does not start it (a period of 0: due at once).
    inside, release = threading.Event(), threading.Event()

    def slow() -> None:
        inside.set()
        release.wait(BOUND)

    first = threading.Thread(target=once_per_period, args=(db, "sweep", 0, "server-a", slow))
    first.start()
    try:
        assert inside.wait(BOUND)
        assert not once_per_period(db, "sweep", 0, "server-b", lambda: ran.append("sweep"))
    finally:
        release.set()
        first.join(BOUND)
    assert once_per_period(db, "sweep", 0, "server-b", lambda: ran.append("sweep"))
    assert ran == ["time-outs", "scrubbing", "sweep"]


@pytest.mark.parametrize("backend", ["postgresql"])
def test_the_capacity_is_timed_by_one_server_at_a_time(db: Database) -> None:
    async def scenario() -> list[str]:
        order: list[str] = []

        async def timing(server: str, entered: asyncio.Event | None = None) -> None:
            async with one_server_at_a_time(db, "capacity"):
                order.append(f"{server} starts")
                if entered is not None:
                    entered.set()
                await asyncio.sleep(0.2)  # the other server waits however long this lasts
                order.append(f"{server} ends")

        entered = asyncio.Event()
        first = asyncio.ensure_future(timing("a", entered))
        await entered.wait()
        await asyncio.gather(first, timing("b"))
        return order

    assert run_apart(scenario) == ["a starts", "a ends", "b starts", "b ends"]


def test_a_second_server_on_a_sqlite_file_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    url = f"sqlite:///{tmp_path / 'study.db'}"
    running = SingleServerLock(url)
    running.acquire()  # a server serves the file
    try:
        with pytest.raises(SecondServer):
            SingleServerLock(url).acquire()
        monkeypatch.setenv("BAM_DATABASE_URL", url)
        monkeypatch.setenv("BAM_ADMIN_TOKEN", ADMIN_TOKEN)
        assert main(["serve", "--port", "1"]) == 1
        error = capsys.readouterr().err
        assert "another server already serves the SQLite database study.db" in error
        assert "use PostgreSQL" in error
        assert not (tmp_path / "study.db").exists()  # refused before touching the database
    finally:
        running.release()
    # Once the first server is gone (a crash too releases its lock), a server may start.
    again = SingleServerLock(url)
    again.acquire()
    again.release()
