"""The schema comes from the Alembic migrations only; `serve` migrates SQLite itself and refuses
an out-of-date PostgreSQL schema with a clear message."""

from __future__ import annotations

import uuid
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import pytest
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from fastapi.testclient import TestClient
from sqlalchemy import func, inspect, select, text

from server.app.main import create_app
from server.app.storage.db import (
    Database,
    SchemaError,
    current_revision,
    downgrade,
    head_revision,
    prepare_schema,
    upgrade,
)
from server.app.storage.models import Base, Installation, Participant
from server.commands.main import main
from tests.support.databases import migrated_postgresql_schema, migrated_sqlite, schema_url
from tests.support.server import POSTGRES_URL, make_settings, study_config


def test_the_migrations_build_exactly_the_models(database_url: str) -> None:
    db = Database.from_url(database_url)
    try:
        assert current_revision(db.engine) is None
        upgrade(db.engine)
        assert current_revision(db.engine) == head_revision()
        with db.engine.connect() as connection:
            context = MigrationContext.configure(connection, opts={"compare_type": True})
            assert compare_metadata(context, Base.metadata) == []
        with db.read() as s:
            secret = s.scalar(select(Installation.secret))
        assert secret is not None and len(secret) == 64
        downgrade(db.engine, "base")
        assert set(inspect(db.engine).get_table_names()) <= {"alembic_version"}
        upgrade(db.engine)
        assert current_revision(db.engine) == head_revision()
    finally:
        db.dispose()


def test_the_tests_copied_databases_are_what_the_migrations_build(db: Database) -> None:
    """The other tests' databases are copies of one the migrations built once
    (tests/support/databases.py): each is at the head, matches the models exactly, and has an
    installation secret of its own, as a database the migrations built would."""
    assert current_revision(db.engine) == head_revision()
    with db.engine.connect() as connection:
        context = MigrationContext.configure(connection, opts={"compare_type": True})
        assert compare_metadata(context, Base.metadata) == []
    with db.read() as s:
        secret = s.scalar(select(Installation.secret))
    assert secret is not None and len(secret) == 64
    with db.write() as s:
        s.add(Participant(token_hash="0" * 64, platform="lab", status="consenting"))
    # A second copy: a secret of its own and none of the first copy's rows.
    if db.is_sqlite:
        other = Database.from_url(
            migrated_sqlite(Path(db.engine.url.database or "").with_name("b.db"))
        )
    else:
        schema = f"test_{uuid.uuid4().hex[:12]}"
        migrated_postgresql_schema(POSTGRES_URL, schema)
        other = Database.from_url(schema_url(POSTGRES_URL, schema))
    try:
        with other.read() as s:
            assert s.scalar(select(Installation.secret)) not in (None, secret)
            assert s.scalar(select(func.count()).select_from(Participant)) == 0
        with db.read() as s:
            assert s.scalar(select(func.count()).select_from(Participant)) == 1
    finally:
        other.dispose()
        if not db.is_sqlite:
            with other.engine.begin() as connection:
                connection.execute(text(f'DROP SCHEMA "{schema}" CASCADE'))


def test_prepare_schema_migrates_sqlite_and_refuses_postgresql(database_url: str) -> None:
    db = Database.from_url(database_url)
    try:
        if db.is_sqlite:
            assert "upgraded" in prepare_schema(db.engine)
            assert "up to date" in prepare_schema(db.engine)
        else:
            with pytest.raises(SchemaError, match="bam-study db upgrade"):
                prepare_schema(db.engine)
            upgrade(db.engine)
            assert "up to date" in prepare_schema(db.engine)
    finally:
        db.dispose()


def test_the_app_does_not_start_on_an_old_schema(
    database_url: str, executor: ProcessPoolExecutor
) -> None:
    db = Database.from_url(database_url)
    try:
        app = create_app(make_settings(database_url), study_config(), db=db, executor=executor)
        with pytest.raises(SchemaError, match="db upgrade"), TestClient(app):
            pass
    finally:
        db.dispose()


def test_the_db_and_serve_commands(database_url: str, capsys: pytest.CaptureFixture[str]) -> None:
    postgres = database_url.startswith("postgresql")
    assert main(["db", "check", "--database-url", database_url]) == 1
    assert "bam-study db upgrade" in capsys.readouterr().out
    if postgres:
        assert main(["serve", "--database-url", database_url]) == 1
        error = capsys.readouterr().err
        assert "this server needs" in error and "bam-study db upgrade" in error
    assert main(["db", "upgrade", "--database-url", database_url]) == 0
    assert "upgraded from none" in capsys.readouterr().out
    assert main(["db", "current", "--database-url", database_url]) == 0
    assert head_revision() in capsys.readouterr().out
    assert main(["db", "check", "--database-url", database_url]) == 0


def test_commands_report_bad_settings(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["db", "check", "--database-url", "mysql://x/y"]) == 2
    assert "sqlite:// or postgresql://" in capsys.readouterr().err
    assert (
        main(["db", "check", "--database-url", "postgresql+psycopg://nobody@127.0.0.1:1/none"]) == 1
    )
    assert "bam-study db:" in capsys.readouterr().err


def test_0003_counts_sessions_started_before_it_as_opened(database_url: str) -> None:
    """Sessions begun under 0002 were taught without an introduction page to come back to: they
    count as opened when they started; the tutorial step starts at 0."""
    from sqlalchemy import text

    db = Database.from_url(database_url)
    try:
        upgrade(db.engine, "0002")
        with db.engine.begin() as c:
            c.execute(
                text(
                    "INSERT INTO participants (id, token_hash, platform, status, next_seq, "
                    "created_at, last_seen_at) VALUES (1, 'h', 'lab', 'teaching', 5, "
                    ":at, :at)"
                ),
                {"at": "2026-01-01 10:00:00+00:00"},
            )
            for number, started in ((1, "2026-01-01 10:01:00+00:00"), (2, None)):
                c.execute(
                    text(
                        "INSERT INTO learning_sessions (id, participant_id, ordinal, kind, "
                        "domain, environment, learner, colour_name, colour_hex, seed, status, "
                        "started_at, completed, task, mode, episode_actions, demonstrated, "
                        "episodes, actions, idle_moves, updates_requested, updates_processed) "
                        "VALUES (:id, 1, :id, 'study', 'navigation', 'wall', 'bam', 'orange', "
                        "'#E69F00', 1, 'active', :started, false, 0, 'idle', 0, '[]', 0, 0, 0, "
                        "0, 0)"
                    ),
                    {"id": number, "started": started},
                )
        upgrade(db.engine)
        with db.engine.connect() as c:
            opened = c.execute(
                text("SELECT id, opened_at FROM learning_sessions ORDER BY id")
            ).all()
            step = c.scalar(text("SELECT tutorial_step FROM participants"))
        assert opened[0][1] is not None and opened[1][1] is None
        assert step == 0
    finally:
        db.dispose()


def test_0010_renames_prolific_status_and_keeps_it(database_url: str) -> None:
    """0010 renames ``participants.prolific_status`` to ``platform_status``: the statuses stored
    before stay, going up and coming back down."""
    from sqlalchemy import text

    db = Database.from_url(database_url)
    try:
        upgrade(db.engine, "0009")
        with db.engine.begin() as c:
            c.execute(
                text(
                    "INSERT INTO participants (id, token_hash, platform, status, next_seq, "
                    "created_at, last_seen_at, prolific_status) VALUES (1, 'h', 'prolific', "
                    "'submitted', 5, :at, :at, 'APPROVED'), (2, 'i', 'lab', 'arrived', 1, :at, "
                    ":at, NULL)"
                ),
                {"at": "2026-01-01 10:00:00+00:00"},
            )
        upgrade(db.engine, "0010")
        with db.engine.connect() as c:
            rows = c.execute(text("SELECT id, platform_status FROM participants ORDER BY id"))
            assert rows.all() == [(1, "APPROVED"), (2, None)]
        downgrade(db.engine, "0009")
        with db.engine.connect() as c:
            rows = c.execute(text("SELECT id, prolific_status FROM participants ORDER BY id"))
            assert rows.all() == [(1, "APPROVED"), (2, None)]
        upgrade(db.engine)
    finally:
        db.dispose()
