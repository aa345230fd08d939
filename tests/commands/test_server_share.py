"""The server's own work per update, timed at start on a scratch copy of the study."""

from __future__ import annotations

import math
import multiprocessing
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy import create_engine, func, select, text
from sqlalchemy.engine import make_url

from server.app.settings import Settings
from server.app.storage.db import Database, upgrade
from server.app.storage.models import LearnerUpdate, Participant
from server.app.study_file import StudyConfig
from server.commands.server_share import (
    SCRATCH_SCHEMA,
    Stopped,
    measure_server_share,
    scratch_database,
    time_server_share,
)
from tests.support.databases import migrated_sqlite
from tests.support.server import POSTGRES_URL, make_settings


def count(db: Database, table: type[Participant] | type[LearnerUpdate]) -> int:
    with db.read() as s:
        return int(s.scalar(select(func.count()).select_from(table)) or 0)


def scratch_schemas(url: str) -> set[str]:
    engine = create_engine(url)
    try:
        with engine.connect() as connection:
            names = connection.scalars(text("SELECT nspname FROM pg_namespace")).all()
    finally:
        engine.dispose()
    return {name for name in names if name.startswith(SCRATCH_SCHEMA)}


@pytest.fixture
def own_database() -> Iterator[str]:
    """A PostgreSQL database of the test's own: the scratch schemas that other tests' servers
    make meanwhile (the tests run side by side) are in another database, not counted here."""
    name = f"bam_share_{uuid.uuid4().hex[:12]}"
    admin = create_engine(POSTGRES_URL, isolation_level="AUTOCOMMIT")
    try:
        with admin.connect() as connection:
            connection.execute(text(f'CREATE DATABASE "{name}"'))
        yield make_url(POSTGRES_URL).set(database=name).render_as_string(hide_password=False)
    finally:
        with admin.connect() as connection:
            connection.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_the_servers_share_is_timed_on_a_scratch_copy_and_not_in_the_study(
    backend: str, study: StudyConfig, tmp_path: Path, request: pytest.FixtureRequest
) -> None:
    if backend == "sqlite":
        url = migrated_sqlite(tmp_path / "study.db")
    else:
        url = request.getfixturevalue("own_database")
    db = Database.from_url(url)
    try:
        if backend == "postgresql":
            upgrade(db.engine)
        _time_the_share(db, make_settings(url), study)
    finally:
        db.dispose()


def _time_the_share(db: Database, settings: Settings, study: StudyConfig) -> None:
    url = settings.database_url
    before = scratch_schemas(url) if not db.is_sqlite else set()
    share = time_server_share(settings, study, participants=2, seconds=3.0, warm_seconds=1.0)
    # CPU seconds of the scratch server's process per update queued: some, and less than
    # the whole of the 3 s the two participants taught for (the updates ran elsewhere).
    assert math.isfinite(share.seconds) and 0 < share.seconds < 3.0
    # On the study's kind of database; a PostgreSQL server on this machine (the tests') works
    # for the scratch study's requests, and its work is counted in the share.
    assert share.database == db.engine.dialect.name
    if db.is_sqlite:
        assert share.database_seconds == 0
    else:
        assert 0 < share.database_seconds < share.seconds
    # The study's own database has no participant and no update of the scratch copy's, and
    # the scratch schema is gone.
    assert count(db, Participant) == 0 and count(db, LearnerUpdate) == 0
    assert (scratch_schemas(url) if not db.is_sqlite else set()) == before


def test_the_float_measured_is_the_shares_seconds(settings: Settings, study: StudyConfig) -> None:
    share = measure_server_share(settings, study, participants=1, seconds=2.0, warm_seconds=1.0)
    assert math.isfinite(share) and 0 < share < 2.0


def test_a_sqlite_studys_scratch_copy_is_a_new_file(tmp_path: Path) -> None:
    study = f"sqlite:///{tmp_path / 'study.db'}"
    with scratch_database(study) as url:
        scratch = Path(make_url(url).database or "")
        assert url.startswith("sqlite:///") and scratch.parent != tmp_path
        assert not scratch.exists()
        scratch.write_bytes(b"")  # as the scratch study's database would be
    assert not scratch.exists()


def test_a_postgresql_studys_scratch_copy_is_a_new_schema_dropped_after(
    own_database: str,
) -> None:
    """First in the search path (the scratch study's tables and its Alembic version go there,
    none of the study's is seen), empty, and gone at the end."""
    before = scratch_schemas(own_database)
    with scratch_database(own_database) as url:
        (schema,) = scratch_schemas(own_database) - before
        scratch = create_engine(url)
        try:
            with scratch.connect() as connection:
                assert connection.scalar(text("SELECT current_schema()")) == schema
                # Its connections named after it (their backends' CPU time is the share's).
                assert connection.scalar(text("SHOW application_name")) == schema
                tables = text("SELECT count(*) FROM pg_tables WHERE schemaname = :s")
                assert connection.scalar(tables, {"s": schema}) == 0
        finally:
            scratch.dispose()
    assert scratch_schemas(own_database) == before


def test_a_scratch_schema_is_dropped_when_the_timing_fails(own_database: str) -> None:
    before = scratch_schemas(own_database)
    with pytest.raises(RuntimeError, match="failed here"):
        with scratch_database(own_database):
            assert len(scratch_schemas(own_database) - before) == 1
            raise RuntimeError("failed here")
    assert scratch_schemas(own_database) == before


def test_without_the_right_to_make_a_schema_the_scratch_copy_is_sqlite(
    caplog: pytest.LogCaptureFixture, own_database: str
) -> None:
    """A database user who may not create a schema (a role that does not own the database):
    the timing runs on SQLite, and says so."""
    role = f"bam_no_create_{uuid.uuid4().hex[:8]}"
    admin = create_engine(POSTGRES_URL)
    try:
        with admin.begin() as connection:
            connection.execute(text(f'CREATE ROLE "{role}" LOGIN'))
        url = make_url(own_database).set(username=role).render_as_string(hide_password=False)
        before = scratch_schemas(own_database)
        with caplog.at_level("WARNING"), scratch_database(url) as scratch:
            assert scratch.startswith("sqlite:///")
        assert "could not make a scratch schema" in caplog.text
        assert scratch_schemas(own_database) == before
    finally:
        with admin.begin() as connection:
            connection.execute(text(f'DROP ROLE IF EXISTS "{role}"'))
        admin.dispose()


def test_a_stopped_timing_ends_its_scratch_study_and_says_so(
    settings: Settings, study: StudyConfig
) -> None:
    """A server stopped while it times its own work does not wait for the timing's end: the
    scratch study stops at once and no process is left behind."""
    stop = threading.Event()
    stop.set()
    before = {child.pid for child in multiprocessing.active_children()}
    started = time.monotonic()
    with pytest.raises(Stopped):
        measure_server_share(settings, study, stop, seconds=600.0, warm_seconds=600.0)
    # Well before the 20 minutes the timing would take (a generous bound: the scratch
    # process starts, and may load the learners, before it sees the stop).
    assert time.monotonic() - started < 300
    assert {child.pid for child in multiprocessing.active_children()} <= before
