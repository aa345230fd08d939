"""The study server's own work per learner update, timed at start for the capacity.

Beside the updates, the server's process answers each participant's requests (the moves, the
agent's steps, the feedback) and reads and stores each update: about 23 requests and some
0.06 s of an AVX-512 AMD EPYC's core for every update a participant queues. On a machine whose
update processes share the cores with it, that work takes from the updates' cores, and the
capacity counts it (``server.app.updates.capacity``).

``measure_server_share`` runs, in a process of its own, a scratch copy of the study: the same
study file and learners, on a new database of the study's kind, served by uvicorn on a free port
of 127.0.0.1 with one update process, and a few simulated participants teaching it as fast as
they can over HTTP. After a few seconds untimed, the server's share is that process's CPU time
less the participants' own (their threads' CPU time), with that of the scratch study's backends
of a PostgreSQL server on this machine (``server.app.storage.database_cpu``; not those of other
clients, a study already under way among them), over the updates queued meanwhile.

The scratch database of a SQLite study is a new file in a temporary folder; that of a
PostgreSQL study is a new schema (``bam_server_share_...``) in the study's database, dropped
at the end (a request on PostgreSQL costs more than on SQLite, and its database's processes
take cores too). Where the study's database user may not create a schema, the scratch copy runs
on SQLite, and the capacity the server shows once participants teach (the live figure) counts
PostgreSQL's work. The study's own tables are never touched.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import signal
import tempfile
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from multiprocessing.connection import Connection

    from server.app.settings import Settings
    from server.app.study_file import StudyConfig

PARTICIPANTS = 6  # teaching the scratch study at once
WARM_SECONDS = 5.0  # untimed: what the server does once only (its first requests, imports)
SECONDS = 20.0  # timed
READY_SECONDS = 600.0  # the scratch server's update process may compile the learners first
SCRATCH_SCHEMA = "bam_server_share_"  # a PostgreSQL study's scratch schemas: this and 12 hex digits

log = logging.getLogger(__name__)


class Stopped(Exception):
    """The timing was stopped (the server that asked for it is stopping)."""


@dataclass(frozen=True)
class ServerShare:
    """What ``time_server_share`` measured: CPU seconds per update queued, the server process's
    and its scratch study's backends' on a local PostgreSQL server together (``seconds``) and
    the backends' alone, and the kind of database the scratch copy ran on."""

    seconds: float
    database_seconds: float
    database: str  # "sqlite" or "postgresql"


def measure_server_share(
    settings: Settings, study: StudyConfig, stop: threading.Event | None = None, **timing: Any
) -> float:
    """The server's CPU seconds per update queued (module docstring): ``time_server_share``'s
    ``seconds`` (``timing``: its keyword arguments), said in the log."""
    share = time_server_share(settings, study, stop, **timing)
    log.info(
        "the server's own work per update: %.4f s of CPU (the database's %.4f s), timed on a "
        "scratch %s copy of the study",
        share.seconds,
        share.database_seconds,
        "PostgreSQL" if share.database == "postgresql" else "SQLite",
    )
    return share.seconds


def time_server_share(
    settings: Settings,
    study: StudyConfig,
    stop: threading.Event | None = None,
    *,
    participants: int = PARTICIPANTS,
    seconds: float = SECONDS,
    warm_seconds: float = WARM_SECONDS,
) -> ServerShare:
    """The server's own work per update queued (module docstring), timed in a process of its
    own so that the calling server's own work is not counted. ``stop``, once set, ends the
    scratch study within a second or two and raises ``Stopped``."""
    context = multiprocessing.get_context("spawn")
    # A pipe both ways (the answer; the word to stop), not a queue or an event: those hold
    # named semaphores, which a server stopped meanwhile would leave behind.
    ours, theirs = context.Pipe()
    # Not a pool's worker: those are daemons, which may not start the scratch server's own
    # update process.
    process = context.Process(
        target=_answer,
        args=(theirs, settings, study, participants, seconds, warm_seconds),
        daemon=False,
    )
    process.start()
    theirs.close()
    told = False
    try:
        while not ours.poll(0.2):
            if stop is not None and stop.is_set() and not told:
                ours.send(STOPPED)
                told = True
            if not process.is_alive() and not ours.poll():
                raise RuntimeError("the scratch study's process ended with no answer")
        share, problem = ours.recv()
    finally:
        if not told and process.is_alive():
            ours.send(STOPPED)
        process.join()
        ours.close()
    if problem is not None:
        raise Stopped(problem) if problem == STOPPED else RuntimeError(problem)
    assert share is not None
    return share


STOPPED = "stopped"


def _answer(connection: Connection, *args: Any) -> None:
    stopping = threading.Event()

    def listen() -> None:  # the word to stop, or the server gone
        with contextlib.suppress(EOFError, OSError):
            connection.recv()
        stopping.set()

    threading.Thread(target=listen, daemon=True).start()
    # A server stopped by a signal to its process group (Ctrl-C, a service manager's SIGTERM)
    # stops this process through ``stopping``, so that its scratch server shuts down in order.
    for number in (signal.SIGINT, signal.SIGTERM):
        signal.signal(number, lambda *_: stopping.set())
    try:
        answer: tuple[ServerShare | None, str | None] = (_scratch_study(stopping, *args), None)
    except Stopped:
        answer = (None, STOPPED)
    except BaseException as error:
        answer = (None, f"{type(error).__name__}: {error}")
    with contextlib.suppress(OSError):
        connection.send(answer)


def _teach(
    base: str,
    index: int,
    stop: threading.Event,
    timing: threading.Event,
    own: list[float],
    errors: list[str],
) -> None:
    """Simulated participant ``index`` takes the scratch study at ``base`` until ``stop``; its
    CPU seconds from the first request once ``timing`` is set go to ``own``, its error (if
    any) to ``errors``."""
    from server.commands.simulated import STUDY_PLAN, SimulatedParticipant

    run = SimulatedParticipant(base, index, 0, STUDY_PLAN, stop=stop)
    started: float | None = None

    def timed(*args: Any, **kwargs: Any) -> Any:
        nonlocal started
        if started is None and timing.is_set():
            started = time.thread_time()
        return send(*args, **kwargs)

    send, run.client.request = run.client.request, timed  # type: ignore[method-assign]
    outcome = run.take_part()
    if started is not None:
        own.append(time.thread_time() - started)
    if outcome.error is not None:
        errors.append(outcome.error)


def _database_cpu(db: Any, url: str) -> Callable[[], float] | None:
    """The reader of the scratch study's own backends' CPU seconds (a scratch schema's
    connections are named after it): not those of a study already under way on the same
    database server (None: no such reader)."""
    from sqlalchemy.engine import make_url

    from server.app.storage.database_cpu import application_cpu_reader

    application = make_url(url).query.get("application_name")
    return application_cpu_reader(db.engine, application) if isinstance(application, str) else None


def _scratch_study(
    stopping: threading.Event,
    settings: Settings,
    study: StudyConfig,
    participants: int,
    seconds: float,
    warm_seconds: float,
) -> ServerShare:
    import uvicorn
    from sqlalchemy import func, select

    from server.app.main import create_app
    from server.app.storage.db import Database, upgrade
    from server.app.storage.models import LearnerUpdate
    from server.commands.live import free_port

    with scratch_database(settings.database_url) as url:
        scratch = settings.model_copy(
            update={"database_url": url, "update_workers": 1, "update_scheduler": None}
        )
        db = Database.from_url(
            url,
            busy_timeout_ms=settings.sqlite_busy_timeout_ms,
            synchronous=settings.sqlite_synchronous,
        )
        upgrade(db.engine)
        database_cpu = _database_cpu(db, url)
        # The simulated participants arrive as from MTurk's replica, whatever the platform:
        # an arrival and a completion are a few of a participant's hundreds of requests.
        copy = study.model_copy(
            update={"completion": study.completion.model_copy(update={"mode": "mturk"})}
        )
        app = create_app(scratch, copy, db=db)
        port = free_port()
        server = uvicorn.Server(
            uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning")
        )
        serving = threading.Thread(target=server.run, daemon=True)
        serving.start()
        try:
            deadline = time.monotonic() + READY_SECONDS
            while not (server.started and app.state.server.updates.ready):
                if not serving.is_alive() or time.monotonic() > deadline:
                    raise RuntimeError("the scratch study's server did not start")
                if stopping.wait(0.1):
                    raise Stopped
            base = f"http://127.0.0.1:{port}"
            stop = threading.Event()
            timing = threading.Event()
            own: list[float] = []  # the participants' CPU seconds while timed
            errors: list[str] = []

            def updates() -> int:
                with db.read() as s:
                    return s.scalar(select(func.count()).select_from(LearnerUpdate)) or 0

            def database() -> float:
                return database_cpu() if database_cpu is not None else 0.0

            threads = [
                threading.Thread(target=_teach, args=(base, i, stop, timing, own, errors))
                for i in range(participants)
            ]
            for thread in threads:
                thread.start()
            try:
                if stopping.wait(warm_seconds):
                    raise Stopped
                before, cpu, database_before = updates(), time.process_time(), database()
                timing.set()
                if stopping.wait(seconds):
                    raise Stopped
            finally:
                stop.set()
                for thread in threads:
                    thread.join()
            # Read before the participants' last requests' effects settle: at most a few
            # requests of the database's work after the stop, against thousands timed.
            database_seconds = database() - database_before
            cpu = time.process_time() - cpu - sum(own)
            queued = updates() - before
            if errors:
                raise RuntimeError(f"a participant of the scratch study failed: {errors[0]}")
            if queued < 1:
                raise RuntimeError("the scratch study's participants queued no update")
            return ServerShare(
                (cpu + database_seconds) / queued,
                database_seconds / queued,
                db.engine.dialect.name,
            )
        finally:
            server.should_exit = True
            serving.join(timeout=30)
            db.dispose()


@contextlib.contextmanager
def scratch_database(study_url: str) -> Iterator[str]:
    """The address of a new, empty database of the study's kind, removed at the end (the
    module docstring): a SQLite file in a temporary folder, or a PostgreSQL schema of the
    study's database, or a SQLite file where that schema cannot be made."""
    from sqlalchemy import create_engine, text
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import SQLAlchemyError
    from sqlalchemy.pool import NullPool

    url = make_url(study_url)
    if url.get_backend_name() == "postgresql":
        schema = f"{SCRATCH_SCHEMA}{uuid.uuid4().hex[:12]}"
        admin = create_engine(url, poolclass=NullPool)
        try:
            with admin.begin() as connection:
                connection.execute(text(f'CREATE SCHEMA "{schema}"'))
        except SQLAlchemyError as error:
            admin.dispose()
            log.warning(
                "could not make a scratch schema in the study's PostgreSQL database (%s); "
                "the server's own work is timed on SQLite, and counted on PostgreSQL once "
                "participants teach",
                str(error).splitlines()[0],
            )
        else:
            try:
                # The schema first in the search path: the scratch study's tables, its Alembic
                # version among them, go there, and nothing of the study's is seen.
                given = url.query.get("options", ())
                options = " ".join(
                    [*((given,) if isinstance(given, str) else given), f"-csearch_path={schema}"]
                )
                # Its connections named after it: their backends' CPU time is the scratch
                # study's (``application_cpu_reader``).
                query = {"options": options, "application_name": schema}
                yield url.update_query_dict(query).render_as_string(hide_password=False)
            finally:
                try:
                    with admin.begin() as connection:
                        connection.execute(text(f'DROP SCHEMA "{schema}" CASCADE'))
                finally:
                    admin.dispose()
            return
    with tempfile.TemporaryDirectory(prefix="bam-server-share-") as folder:
        yield f"sqlite:///{Path(folder) / 'scratch.db'}"
