"""Durability and readiness: SQLite commits with synchronous=FULL unless told otherwise; the
server reports ready (/api/health 200) only once every learner-update process has loaded the
learners' kernels, and ``serve`` says on the console what it waits for."""

from __future__ import annotations

import multiprocessing
import re
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import text

from server.app.main import create_app
from server.app.settings import Settings
from server.app.storage.db import Database
from server.commands.live import ServerProcess
from tests.app.test_live import fast_study_file
from tests.support.server import ADMIN_TOKEN, make_settings, study_config

WARM_UP_SECONDS = 3.0


@pytest.mark.parametrize(("setting", "pragma"), [(None, 2), ("full", 2), ("normal", 1)])
def test_sqlite_commits_are_synchronous_full_by_default(
    tmp_path: Path, setting: str | None, pragma: int
) -> None:
    url = f"sqlite:///{tmp_path / 'study.db'}"
    settings = Settings(database_url=url, **({"sqlite_synchronous": setting} if setting else {}))
    db = Database.from_url(url, synchronous=settings.sqlite_synchronous)
    try:
        with db.connect() as c:
            assert c.execute(text("PRAGMA synchronous")).scalar() == pragma
            assert c.execute(text("PRAGMA journal_mode")).scalar() == "wal"
    finally:
        db.dispose()
    with pytest.raises(ValueError):
        Settings(database_url=url, sqlite_synchronous="off")


def test_health_is_starting_until_every_update_process_is_warm(db: Database) -> None:
    # Processes that take WARM_UP_SECONDS to start, as loading (or compiling) the kernels does.
    slow = ProcessPoolExecutor(
        2,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=time.sleep,
        initargs=(WARM_UP_SECONDS,),
    )
    settings = make_settings(db.engine.url.render_as_string(hide_password=False))
    app = create_app(settings, study_config(), db=db, executor=slow)
    try:
        with TestClient(app) as client:
            began = time.monotonic()
            first = client.get("/api/health")
            assert first.status_code == 503
            assert first.json()["status"] == "starting"
            assert "kernels" in first.json()["detail"]
            assert first.json()["update_processes_warm"] < 2
            # Requests are served meanwhile.
            assert client.get("/api/study").status_code == 200
            while (answer := client.get("/api/health")).status_code == 503:
                assert time.monotonic() - began < 60
                time.sleep(0.05)
            assert answer.status_code == 200 and answer.json()["status"] == "ok"
            assert answer.json()["update_processes_warm"] == 2
            assert time.monotonic() - began > WARM_UP_SECONDS - 1
    finally:
        slow.shutdown(wait=True, cancel_futures=True)


@pytest.mark.slow
def test_serve_says_what_it_waits_for_and_is_ready_after_its_update_processes(
    db: Database, tmp_path: Path
) -> None:
    environment = {
        "BAM_DATABASE_URL": db.engine.url.render_as_string(hide_password=False),
        "BAM_ADMIN_TOKEN": ADMIN_TOKEN,
        "BAM_STUDY_CONFIG": str(fast_study_file(tmp_path)),
        "BAM_UPDATE_WORKERS": "2",
    }
    with ServerProcess(tmp_path, environment) as server:  # started: /api/health answered 200
        log = server.log()
    waiting = log.index("waiting for 2 update process(es) to load the learners' compiled kernels")
    ready = log.index("the server is ready")
    processes = [m.start() for m in re.finditer(r"update process \d+ ready in", log)]
    assert len(processes) == 2
    assert waiting < min(processes) and max(processes) < ready
