"""Alembic environment: runs the migrations on the connection ``bam-study`` hands over, or on
BAM_DATABASE_URL when Alembic is run by hand."""

from __future__ import annotations

from alembic import context
from sqlalchemy import Connection
from sqlalchemy.pool import NullPool

import server.app.storage.replica_models  # noqa: F401  (its tables are in Base.metadata too)
from server.app.settings import Settings
from server.app.storage.db import create_db_engine, migration_connection
from server.app.storage.models import Base

config = context.config
target_metadata = Base.metadata


def run(connection: Connection) -> None:
    context.configure(
        connection=connection,
        target_metadata=target_metadata,
        render_as_batch=connection.dialect.name == "sqlite",
        compare_type=True,
    )
    with context.begin_transaction():
        context.run_migrations()


def run_online() -> None:
    connection = config.attributes.get("connection")
    if connection is not None:
        run(connection)
        return
    url = config.attributes.get("database_url") or Settings().database_url
    engine = create_db_engine(url, poolclass=NullPool)
    try:
        with migration_connection(engine) as connection:  # SQLite: foreign keys off, checked
            run(connection)
    finally:
        engine.dispose()


if context.is_offline_mode():
    raise SystemExit("offline (--sql) migrations are not supported; run them on a database")
run_online()
