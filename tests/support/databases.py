"""Migrated databases for the tests, built once per test process and copied for each test.

The Alembic migrations run once for SQLite (into a template file) and once for PostgreSQL
(into a template schema, dumped with ``pg_dump`` and dropped). Each test then gets its own copy:
the file copied, or the dump replayed under a new schema name; the copy's installation secret
(the pseudonyms' key) is drawn anew, as a real migration draws it. ``tests/app/storage/test_migrations.py`` still runs the
real migrations on empty databases, so what they build stays tested; this only spares the
hundreds of tests that need *a* migrated database from running nine revisions each.
"""

from __future__ import annotations

import atexit
import secrets
import shutil
import sqlite3
import subprocess
import tempfile
import uuid
from functools import cache
from pathlib import Path

from sqlalchemy import create_engine, text
from sqlalchemy.engine import make_url
from sqlalchemy.pool import NullPool

from server.app.storage.db import Database, upgrade


@cache
def _sqlite_template() -> Path:
    folder = Path(tempfile.mkdtemp(prefix="bam-test-template-"))
    atexit.register(shutil.rmtree, folder, True)
    path = folder / "template.db"
    database = Database.from_url(f"sqlite:///{path}")
    try:
        upgrade(database.engine)
        with database.engine.connect() as connection:
            connection.exec_driver_sql("PRAGMA wal_checkpoint(TRUNCATE)")
    finally:
        database.dispose()
    return path


def migrated_sqlite(path: Path) -> str:
    """A SQLite database at ``path`` at the migrations' head (a copy of the template); its URL."""
    shutil.copyfile(_sqlite_template(), path)
    connection = sqlite3.connect(path)
    try:
        connection.execute("UPDATE installation SET secret = ?", (secrets.token_hex(32),))
        connection.commit()
    finally:
        connection.close()
    return f"sqlite:///{path}"


def schema_url(server_url: str, schema: str) -> str:
    """``server_url`` with its connections' search path set to ``schema``."""
    # Commits unflushed: the tests never crash PostgreSQL itself (a killed study server loses
    # nothing either way), and a commit waits for no disk.
    options = f"-csearch_path={schema} -csynchronous_commit=off"
    url = make_url(server_url).update_query_dict({"options": options})
    return url.render_as_string(hide_password=False)


@cache
def _postgresql_dump(server_url: str) -> tuple[str, str] | None:
    """The migrated schema as SQL and the placeholder name it uses; None without ``pg_dump``."""
    pg_dump = shutil.which("pg_dump")
    if pg_dump is None:
        return None
    name = f"bam_template_{uuid.uuid4().hex}"
    admin = create_engine(server_url, poolclass=NullPool)
    try:
        with admin.begin() as connection:
            connection.execute(text(f'CREATE SCHEMA "{name}"'))
        try:
            database = Database.from_url(schema_url(server_url, name))
            try:
                upgrade(database.engine)
            finally:
                database.dispose()
            url = make_url(server_url)
            dumped = subprocess.run(
                [pg_dump, "--schema", name, "--inserts", "--no-owner", "--no-privileges"]
                + (["--host", url.host] if url.host else [])
                + (["--port", str(url.port)] if url.port else [])
                + (["--username", url.username] if url.username else [])
                + [url.database or "postgres"],
                capture_output=True,
                text=True,
                check=True,
            ).stdout
        finally:
            with admin.begin() as connection:
                connection.execute(text(f'DROP SCHEMA "{name}" CASCADE'))
    finally:
        admin.dispose()
    # psql's meta-commands (\restrict and \unrestrict) are not SQL.
    sql = "\n".join(line for line in dumped.splitlines() if not line.startswith("\\"))
    return sql, name


def migrated_postgresql_schema(server_url: str, schema: str) -> None:
    """Create ``schema`` on the server at the migrations' head (the template's dump replayed
    under that name, or the migrations run on it where ``pg_dump`` is missing)."""
    dump = _postgresql_dump(server_url)
    admin = create_engine(server_url, poolclass=NullPool)
    try:
        with admin.begin() as connection:
            if dump is None:
                connection.execute(text(f'CREATE SCHEMA "{schema}"'))
            else:
                sql, name = dump
                connection.exec_driver_sql(sql.replace(name, schema))
                connection.execute(
                    text(f'UPDATE "{schema}".installation SET secret = :secret'),
                    {"secret": secrets.token_hex(32)},
                )
    finally:
        admin.dispose()
    if dump is None:
        database = Database.from_url(schema_url(server_url, schema))
        try:
            upgrade(database.engine)
        finally:
            database.dispose()
