"""Fixtures of the study server's tests: a fresh database per test on SQLite and on PostgreSQL
(a copy of one the Alembic migrations built once, tests/support/databases.py), the app with a shared pool of update processes, and a small
client that keeps the participant's sequence number."""

from __future__ import annotations

import asyncio
import os
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from concurrent.futures import Executor, Future, ProcessPoolExecutor, ThreadPoolExecutor
from contextlib import contextmanager
from typing import Any

import httpx
import pytest
import uvicorn
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import create_engine, func, select, text

from server.app.main import create_app
from server.app.participants.tokens import TOKEN_HEADER
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import Event, LearnerUpdate
from server.app.study_file import DEFAULT_STUDY_CONFIG, StudyConfig, parse_study_config
from server.app.updates.pool import new_executor
from server.app.updates.worker import run_update
from server.commands.live import free_port
from server.commands.serve import server_config
from tests.support.databases import migrated_postgresql_schema, migrated_sqlite, schema_url

POSTGRES_URL = os.environ.get(
    "BAM_TEST_POSTGRES_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/test"
)
ADMIN_TOKEN = "test-admin-token"
BOUND = 60.0  # seconds: a generous bound on anything that should happen at once
MTURK = "https://workersandbox.mturk.com"

# Learner settings that keep updates to a fraction of a second (the real learners, fewer steps).
FAST_LEARNERS = {
    "bam": {"alternations": 1, "cost_steps": 4, "dynamics_steps": 4},
    "model-based": {"dynamics_steps": 6, "cost_steps": 6},
    "cloning": {"steps": 20},
}


def study_config(**changes: Any) -> StudyConfig:
    """The paper's study with fast learner settings, and ``changes`` on top."""
    import tomllib

    data = tomllib.loads(DEFAULT_STUDY_CONFIG.read_text())
    data["learner_settings"] = FAST_LEARNERS
    for key, value in changes.items():
        if isinstance(value, dict) and isinstance(data.get(key), dict):
            data[key] = {**data[key], **value}
        else:
            data[key] = value
    return parse_study_config(data, "test study")


@pytest.fixture(scope="session")
def executor() -> Iterator[ProcessPoolExecutor]:
    pool = new_executor(2, 0)
    yield pool
    pool.shutdown(wait=True, cancel_futures=True)


@pytest.fixture(params=["sqlite", "postgresql"])
def backend(request: pytest.FixtureRequest) -> str:
    """The database a test runs on: every database test runs on SQLite and on PostgreSQL."""
    return str(request.param)


@contextmanager
def _postgresql_schema(migrated: bool) -> Iterator[str]:
    """A new PostgreSQL schema (empty, or at the migrations' head), dropped afterwards."""
    schema = f"test_{uuid.uuid4().hex[:12]}"
    admin = create_engine(POSTGRES_URL)
    try:
        if migrated:
            migrated_postgresql_schema(POSTGRES_URL, schema)
        else:
            with admin.begin() as connection:
                connection.execute(text(f'CREATE SCHEMA "{schema}"'))
    except Exception as error:  # pragma: no cover - the environment is broken
        admin.dispose()
        pytest.fail(
            f"PostgreSQL at {POSTGRES_URL} is not available ({error}); start it with "
            "pg_ctlcluster --skip-systemctl-redirect $(ls /etc/postgresql) main start"
        )
    try:
        yield schema_url(POSTGRES_URL, schema)
    finally:
        with admin.begin() as connection:
            connection.execute(text(f'DROP SCHEMA "{schema}" CASCADE'))
        admin.dispose()


@pytest.fixture
def database_url(backend: str, tmp_path: Any) -> Iterator[str]:
    """An empty database: a SQLite file, or a new PostgreSQL schema dropped afterwards."""
    if backend == "sqlite":
        yield f"sqlite:///{tmp_path / 'study.db'}"
        return
    with _postgresql_schema(migrated=False) as url:
        yield url


@pytest.fixture
def db(backend: str, tmp_path: Any) -> Iterator[Database]:
    """A fresh database at the latest schema (a copy of one the migrations built once)."""
    if backend == "sqlite":
        database = Database.from_url(migrated_sqlite(tmp_path / "study.db"))
        yield database
        database.dispose()
        return
    with _postgresql_schema(migrated=True) as url:
        database = Database.from_url(url)
        yield database
        database.dispose()


class Gated(Executor):
    """Runs ``run_update`` in a thread, but only once the gate is open (an update held as long
    as a test needs, whatever the machine's speed); records each job's learner seed (which
    names its session) in the order the updates were started."""

    def __init__(self) -> None:
        self.gate = threading.Event()
        self.gate.set()
        self.started: list[int] = []
        self.lock = threading.Lock()
        self.pool = ThreadPoolExecutor(1)

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future[Any]:
        def held() -> Any:
            if fn is run_update:
                self.gate.wait(BOUND)
                with self.lock:
                    self.started.append(int(args[0]["seed"]))
            return fn(*args, **kwargs)

        return self.pool.submit(held)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self.gate.set()
        self.pool.shutdown(wait=wait, cancel_futures=cancel_futures)


def gated_app(db: Database, settings: Settings, study: StudyConfig) -> tuple[FastAPI, Gated]:
    """The app with one update process (the gated pool's one thread) to warm up and run the
    updates, and an agent step that waits as long as the tests' bound."""
    gated = Gated()
    one = settings.model_copy(update={"update_workers": 1, "agent_wait_seconds": BOUND})
    return create_app(one, study, db=db, executor=gated), gated


def make_settings(database_url: str, **changes: Any) -> Settings:
    return Settings(database_url=database_url, admin_token=ADMIN_TOKEN, **changes)


@pytest.fixture
def study() -> StudyConfig:
    return study_config()


@pytest.fixture
def settings(db: Database) -> Settings:
    return make_settings(db.engine.url.render_as_string(hide_password=False))


@pytest.fixture
def client(
    db: Database, settings: Settings, study: StudyConfig, executor: ProcessPoolExecutor
) -> Iterator[TestClient]:
    app = create_app(settings, study, db=db, executor=executor)
    with TestClient(app) as test_client:
        yield test_client


@contextmanager
def live(app: FastAPI, log_level: str = "warning", access_log: bool = False) -> Iterator[str]:
    """``app`` served by uvicorn in a thread on a free port, as ``serve`` runs it (one lifespan,
    real HTTP); yields its base URL."""
    port = free_port()
    settings = app.state.server.settings
    config = server_config(app, settings, "127.0.0.1", port, log_level, access_log)
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, name=f"live-server-{port}", daemon=True)
    thread.start()
    deadline = time.monotonic() + 60
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            raise RuntimeError("the live server did not start")
        time.sleep(0.05)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(timeout=60)


class Participant:
    """A participant talking to the API: keeps the token and the next sequence number."""

    def __init__(self, client: httpx.Client, token: str, next_seq: int = 1) -> None:
        self.client = client
        self.token = token
        self.seq = next_seq

    @property
    def headers(self) -> dict[str, str]:
        return {TOKEN_HEADER: self.token}

    def get(self, path: str) -> Any:
        response = self.client.get(path, headers=self.headers)
        assert response.status_code == 200, response.text
        return response.json()

    def post(self, path: str, **body: Any) -> Any:
        """A raw POST with the next seq (not checked, not advanced)."""
        return self.client.post(path, json={"seq": self.seq, **body}, headers=self.headers)

    def act(self, path: str, **body: Any) -> Any:
        response = self.post(path, **body)
        assert response.status_code == 200, response.text
        data = response.json()
        self.seq = data["participant"]["next_seq"]
        return data

    def session(self, session_id: int) -> str:
        return f"/api/sessions/{session_id}"


def arrive(client: httpx.Client, worker: str = "W1", assignment: str = "A1", **extra: Any) -> Any:
    params = {
        "assignmentId": assignment,
        "hitId": "H1",
        "workerId": worker,
        "turkSubmitTo": MTURK,
        **extra,
    }
    return client.post("/api/arrivals", json=params)


def new_participant(
    client: httpx.Client, worker: str = "W1", assignment: str = "A1"
) -> Participant:
    response = arrive(client, worker, assignment)
    assert response.status_code == 201, response.text
    return Participant(client, response.json()["token"])


def teaching_participant(
    client: httpx.Client, worker: str = "W1", assignment: str = "A1"
) -> tuple[Participant, int]:
    """A participant past consent and start: returns it and its current (tutorial) session."""
    participant = new_participant(client, worker, assignment)
    participant.act("/api/participant/consent", agree=True)
    data = participant.act("/api/participant/start")
    return participant, data["participant"]["current_session_id"]


def wait_until_ready(client: httpx.Client, timeout: float = 120.0) -> dict[str, Any]:
    """Until /api/health answers 200 (every update process warm); its answer."""
    deadline = time.monotonic() + timeout
    while (response := client.get("/api/health")).status_code == 503:
        if time.monotonic() > deadline:
            raise AssertionError(f"not ready after {timeout} s: {response.text}")
        time.sleep(0.05)
    assert response.status_code == 200, response.text
    return dict(response.json())


def wait_until(condition: Callable[[], bool], what: str, timeout: float = 120.0) -> None:
    """Until ``condition()`` holds (an AssertionError naming ``what`` after ``timeout`` s)."""
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.02)


def run_apart(scenario: Callable[[], Any]) -> Any:
    """``asyncio.run(scenario())`` in a thread of its own: after the browser tests, this
    thread may run an event loop, where ``asyncio.run`` refuses."""
    with ThreadPoolExecutor(1) as pool:
        return pool.submit(asyncio.run, scenario()).result()


def count_events(db: Database) -> int:
    with db.read() as s:
        return int(s.scalar(select(func.count()).select_from(Event)) or 0)


def wait_for_updates(db: Database, timeout: float = 120.0) -> None:
    """Until no learner update is pending."""
    deadline = time.monotonic() + timeout
    while True:
        with db.read() as s:
            pending = s.scalar(
                select(func.count())
                .select_from(LearnerUpdate)
                .where(LearnerUpdate.status == "pending")
            )
        if not pending:
            return
        if time.monotonic() > deadline:
            raise AssertionError(f"{pending} learner updates still pending after {timeout} s")
        time.sleep(0.05)


def demonstrate_each_task(participant: Participant, session_id: int) -> None:
    """One demonstrated action per task (enough to finish the agent)."""
    base = participant.session(session_id)
    view = participant.get(base)
    participant.act(f"{base}/mode", mode="demonstrate")
    for task in range(len(view["environment"]["tasks"])):
        participant.act(f"{base}/task", task=task)
        if participant.get(base)["teaching"]["mode"] != "demonstrate":
            participant.act(f"{base}/mode", mode="demonstrate")
        participant.act(f"{base}/move", action="RIGHT" if task % 2 else "LEFT")
