"""The schema comes from the Alembic migrations only; `serve` migrates SQLite itself and refuses
an out-of-date PostgreSQL schema with a clear message."""

from __future__ import annotations

import json
import uuid
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import pytest
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from fastapi.testclient import TestClient
from sqlalchemy import func, inspect, select, text
from sqlalchemy.exc import IntegrityError

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


# What 0019 renames: (table at 0018, its columns there) -> (table at 0019, the same columns).
RENAMED_0019 = {
    ("participants", "id, worker_id, assignment_id, hit_id"): (
        "participants",
        "id, platform_participant_id, platform_submission_id, platform_study_id",
    ),
    ("assignment_reviews", "id, participant_id, assignment_id, worker_id, message"): (
        "reviews",
        "id, participant_id, platform_submission_id, platform_participant_id, message",
    ),
    ("bonuses", "id, participant_id, assignment_id, worker_id, amount_cents"): (
        "bonuses",
        "id, participant_id, platform_submission_id, platform_participant_id, amount_cents",
    ),
    ("messages", "id, participant_id, worker_id, study_id"): (
        "messages",
        "id, participant_id, platform_participant_id, study_id",
    ),
    ("erasures", "id, worker_pseudonym, assignment_pseudonym"): (
        "erasures",
        "id, platform_participant_pseudonym, platform_submission_pseudonym",
    ),
    ("status_changes", "id, participant_id, status"): (
        "status_changes",
        "id, participant_id, status",
    ),
}


def _rows_0019(c: Any, renamed: bool) -> dict[str, list[tuple[Any, ...]]]:
    return {
        old_table: [
            tuple(row)
            for row in c.execute(
                text(
                    f"SELECT {new[1] if renamed else columns} "
                    f"FROM {new[0] if renamed else old_table} ORDER BY id"
                )
            )
        ]
        for (old_table, columns), new in RENAMED_0019.items()
    }


def test_0019_renames_the_platform_ids_and_the_reviews_and_keeps_every_row(
    database_url: str,
) -> None:
    """0019 names a participant's platform ids for any platform (``platform_participant_id``,
    ``platform_submission_id``, ``platform_study_id``) and ``assignment_reviews`` ``reviews``:
    the rows written at 0018, in the renamed tables and in the rows that refer to them, are
    found under the new names going up and under the old ones coming back down, and the
    constraints still hold under their new names."""
    db = Database.from_url(database_url)
    at = {"at": "2026-01-01 10:00:00+00:00"}
    try:
        upgrade(db.engine, "0018")
        with db.engine.begin() as c:
            c.execute(
                text(
                    "INSERT INTO participants (id, token_hash, platform, worker_id, assignment_id, "
                    "hit_id, status, next_seq, created_at, last_seen_at) VALUES "
                    "(1, 'h', 'prolific', 'PID1', 'SESSION1', 'STUDY1', 'submitted', 5, :at, :at), "
                    "(2, 'i', 'lab', NULL, NULL, NULL, 'arrived', 1, :at, :at)"
                ),
                at,
            )
            c.execute(
                text(
                    "INSERT INTO status_changes (id, participant_id, status, at) VALUES "
                    "(1, 1, 'arrived', :at), (2, 1, 'submitted', :at), (3, 2, 'arrived', :at)"
                ),
                at,
            )
            c.execute(
                text(
                    "INSERT INTO assignment_reviews (id, participant_id, assignment_id, worker_id, "
                    "decision, message, backend, state, requested_at, decided_at) VALUES "
                    "(1, 1, 'SESSION1', 'PID1', 'approved', 'Thanks', 'prolific', 'done', :at, :at)"
                ),
                at,
            )
            c.execute(
                text(
                    "INSERT INTO bonuses (id, participant_id, assignment_id, worker_id, "
                    "amount_cents, currency, reason, unique_token, backend, state, requested_at) "
                    "VALUES (1, 1, 'SESSION1', 'PID1', 125, 'GBP', 'Well taught', 't1', "
                    "'prolific', 'paid', :at)"
                ),
                at,
            )
            c.execute(
                text(
                    "INSERT INTO messages (id, participant_id, worker_id, study_id, body, backend, "
                    "sent_with, answer_status, sent_at) VALUES (1, 1, 'PID1', 'STUDY1', 'Hello', "
                    "'prolific', 'messages', 204, :at)"
                ),
                at,
            )
            c.execute(
                text(
                    "INSERT INTO erasures (id, erased_at, erased_by, participant_id, platform, "
                    "worker_pseudonym, assignment_pseudonym, rows) VALUES (1, :at, "
                    "'experimenter', 9, 'mturk', 'w_1', 'a_1', :rows)"
                ),
                {**at, "rows": json.dumps({"participants": 1, "assignment_reviews": 1})},
            )
        with db.engine.connect() as c:
            before = _rows_0019(c, renamed=False)
        assert all(before.values())

        upgrade(db.engine, "0019")
        with db.engine.connect() as c:
            assert _rows_0019(c, renamed=True) == before
            rows = c.scalar(text("SELECT rows FROM erasures"))
            assert (json.loads(rows) if isinstance(rows, str) else rows) == {
                "participants": 1,
                "reviews": 1,
            }
        inspector = inspect(db.engine)
        assert "assignment_reviews" not in inspector.get_table_names()
        assert {u["name"] for u in inspector.get_unique_constraints("participants")} >= {
            "uq_participants_platform_ids"
        }
        assert {i["name"] for i in inspector.get_indexes("participants")} >= {
            "ix_participants_platform_participant_id"
        }
        assert {u["name"] for u in inspector.get_unique_constraints("reviews")} == {
            "uq_reviews_platform_submission_id",
            "uq_reviews_participant_id",
        }
        with pytest.raises(IntegrityError), db.engine.begin() as c:  # still one review each
            c.execute(
                text(
                    "INSERT INTO reviews (participant_id, platform_submission_id, "
                    "platform_participant_id, decision, backend, state, requested_at) VALUES "
                    "(1, 'SESSION2', 'PID1', 'approved', 'prolific', 'done', :at)"
                ),
                at,
            )
        with pytest.raises(IntegrityError), db.engine.begin() as c:  # and to a participant
            c.execute(
                text(
                    "INSERT INTO reviews (participant_id, platform_submission_id, "
                    "platform_participant_id, decision, backend, state, requested_at) VALUES "
                    "(7, 'SESSION7', 'PID7', 'approved', 'prolific', 'done', :at)"
                ),
                at,
            )
        with db.engine.connect() as connection:
            context = MigrationContext.configure(connection, opts={"compare_type": True})
            assert compare_metadata(context, Base.metadata) == []

        downgrade(db.engine, "0018")
        with db.engine.connect() as c:
            assert _rows_0019(c, renamed=False) == before
            rows = c.scalar(text("SELECT rows FROM erasures"))
            assert (json.loads(rows) if isinstance(rows, str) else rows) == {
                "participants": 1,
                "assignment_reviews": 1,
            }
        inspector = inspect(db.engine)
        assert "reviews" not in inspector.get_table_names()
        assert {u["name"] for u in inspector.get_unique_constraints("assignment_reviews")} == {
            "uq_assignment_reviews_assignment_id",
            "uq_assignment_reviews_participant_id",
        }
        assert {i["name"] for i in inspector.get_indexes("participants")} >= {
            "ix_participants_worker_id"
        }
        upgrade(db.engine)
    finally:
        db.dispose()
