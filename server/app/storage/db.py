"""Database engines, transactions and the Alembic migrations.

SQLite (the embedded default) runs in WAL mode with a busy timeout and foreign keys on, and
with ``synchronous=FULL`` by default: every commit (every acknowledged request) is on disk
before it is answered, through an OS crash or power loss too. ``NORMAL``
(``BAM_SQLITE_SYNCHRONOUS=normal``) survives a crash of the server process but may lose the
last commits to an OS crash or power loss. All of
one server's writes go through ``Database.write()``: on SQLite they queue on a lock inside the
process and open with ``BEGIN IMMEDIATE``, so concurrent participants never see "database is
locked" and never wait in SQLite's sleeping busy handler; on PostgreSQL each transaction locks
the participant's row instead (``lock_participant``), so concurrent requests of different
participants run in parallel.
"""

from __future__ import annotations

import hashlib
import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any
from urllib.parse import quote

from sqlalchemy import Connection, Engine, create_engine, event
from sqlalchemy.engine import make_url
from sqlalchemy.exc import ArgumentError
from sqlalchemy.orm import Session, sessionmaker
from sqlalchemy.pool import NullPool

# The source tree: alembic.ini and migrations/ sit at its root (editable installs and the
# Docker image both run from the tree).
ROOT = Path(__file__).resolve().parents[3]
ALEMBIC_INI = ROOT / "alembic.ini"
MIGRATIONS = ROOT / "migrations"


class SchemaError(RuntimeError):
    """The database schema is not at the version this code needs."""


def advisory_lock_key(name: str) -> int:
    """A PostgreSQL advisory lock key: the first 8 bytes of sha256(name)."""
    return int.from_bytes(hashlib.sha256(name.encode()).digest()[:8], "big", signed=True)


SQLITE_SYNCHRONOUS = ("full", "normal")


def create_db_engine(
    url: str,
    busy_timeout_ms: int = 10_000,
    pool_size: int = 20,
    synchronous: str = "full",
    **kwargs: Any,
) -> Engine:
    """An engine for ``url`` with the settings the study server relies on."""
    parsed = make_url(url)
    if kwargs.get("poolclass") is not NullPool:
        kwargs.update(pool_size=pool_size, max_overflow=pool_size)
    if parsed.get_backend_name() == "sqlite":
        if parsed.database in (None, "", ":memory:"):
            raise ValueError("the study needs a SQLite file, not an in-memory database")
        connect_args = {"check_same_thread": False, "timeout": busy_timeout_ms / 1000}
        engine = create_engine(url, connect_args=connect_args, **kwargs)
        if synchronous not in SQLITE_SYNCHRONOUS:
            raise ValueError(f"SQLite synchronous must be one of {SQLITE_SYNCHRONOUS}")
        _configure_sqlite(engine, busy_timeout_ms, synchronous)
        return engine
    return create_engine(url, pool_pre_ping=True, **kwargs)


def _configure_sqlite(engine: Engine, busy_timeout_ms: int, synchronous: str) -> None:
    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_connection: Any, _record: Any) -> None:
        # Take over BEGIN from the driver so that writes can BEGIN IMMEDIATE (see do_begin).
        dbapi_connection.isolation_level = None
        cursor = dbapi_connection.cursor()
        cursor.execute("PRAGMA journal_mode=WAL")
        cursor.execute(f"PRAGMA busy_timeout={int(busy_timeout_ms)}")
        cursor.execute("PRAGMA foreign_keys=ON")
        cursor.execute(f"PRAGMA synchronous={synchronous.upper()}")
        # What is deleted is overwritten with zeros, not left in free pages: an erasure or a
        # scrub leaves no raw id in the file (Debian's SQLite defaults to it; others do not).
        cursor.execute("PRAGMA secure_delete=ON")
        cursor.close()

    @event.listens_for(engine, "begin")
    def _do_begin(connection: Any) -> None:
        immediate = connection.get_execution_options().get("sqlite_immediate", False)
        # On the driver's connection: a statement through SQLAlchemy's execution costs more
        # than the BEGIN itself, and every request begins one.
        connection.connection.dbapi_connection.execute("BEGIN IMMEDIATE" if immediate else "BEGIN")


class Database:
    """An engine with read and write transactions (see the module docstring)."""

    def __init__(self, engine: Engine, *, read_only: bool = False) -> None:
        self.engine = engine
        self.read_only = read_only  # opened to read (``open_study_database``): never written
        self.is_sqlite = engine.dialect.name == "sqlite"
        self._write_lock = threading.Lock() if self.is_sqlite else None
        self._write_engine = (
            engine.execution_options(sqlite_immediate=True) if self.is_sqlite else engine
        )
        self._writing: Connection | None = None  # SQLite's writes' connection (``transaction``)
        self._reader = sessionmaker(engine, expire_on_commit=False, autoflush=False)
        self._writer = sessionmaker(self._write_engine, expire_on_commit=False, autoflush=False)

    @classmethod
    def from_url(cls, url: str, **kwargs: Any) -> Database:
        return cls(create_db_engine(url, **kwargs))

    @contextmanager
    def read(self) -> Iterator[Session]:
        # Closing (not rolling back) keeps the objects read usable after the block; the pool
        # ends the transaction when the connection goes back.
        with self._reader() as session:
            yield session

    @contextmanager
    def write(self) -> Iterator[Session]:
        """A write transaction, committed when the block ends without an exception."""
        if self._write_lock is None:
            with self._writer.begin() as session:
                yield session
            return
        with self._write_lock, self._writer.begin() as session:
            yield session

    @contextmanager
    def transaction(self) -> Iterator[Connection]:
        """A write transaction on a Core connection (the request path; see ``records.py``).
        On SQLite, where one write runs at a time, every one runs on the same connection,
        kept open: the pool's checkout, reset and checkin were a tenth of a request's CPU."""
        if self._write_lock is None:
            with self._write_engine.begin() as connection:
                yield connection
            return
        with self._write_lock:
            if self._writing is None or self._writing.closed or self._writing.invalidated:
                self._writing = self._write_engine.connect()
            with self._writing.begin():
                yield self._writing

    @contextmanager
    def connect(self) -> Iterator[Connection]:
        """A read-only Core connection."""
        with self.engine.connect() as connection:
            yield connection

    def forget_removed(self) -> bool:
        """After an erasure or a scrub, take what it deleted or overwrote out of the files as
        well as the rows: on SQLite the write-ahead log, which still holds the pages as they
        were, is checkpointed into the database (whose deleted content ``secure_delete``
        zeroed) and truncated to nothing; on PostgreSQL the tables that hold platform ids are
        rewritten with their indexes (``VACUUM FULL``: small tables, a row or a few per
        participant), so no dead row or index entry keeps the id. Returns False where readers
        kept SQLite's log busy past a quarter of a second (the study's requests are not held
        longer): the next erasure, scrub or the server's stop truncates it."""
        if self.is_sqlite:
            return _truncate_wal(self.engine, busy_timeout_ms=250)
        with self.engine.connect().execution_options(isolation_level="AUTOCOMMIT") as c:
            for name in PLATFORM_ID_TABLES:
                c.exec_driver_sql(f'VACUUM FULL "{name}"')
        return True

    def dispose(self) -> None:
        if self._write_lock is not None and not self.read_only:
            with self._write_lock:
                if self._writing is not None:
                    self._writing.close()
                    self._writing = None
            # Nothing of the log's past pages (an erased participant's, say) left beside the
            # database after a stop.
            _truncate_wal(self.engine, busy_timeout_ms=1000)
        self.engine.dispose()


def _truncate_wal(engine: Engine, busy_timeout_ms: int) -> bool:
    """Checkpoint SQLite's write-ahead log into the database and truncate it; False where
    readers or a writer kept it busy for ``busy_timeout_ms``."""
    try:
        with engine.connect() as connection:
            connection.exec_driver_sql(f"PRAGMA busy_timeout={int(busy_timeout_ms)}")
            busy, _, _ = connection.exec_driver_sql("PRAGMA wal_checkpoint(TRUNCATE)").one()
            connection.invalidate()  # closed, not pooled with the short timeout
    except Exception:  # a database already gone (a test's folder removed): nothing to truncate
        return False
    return not busy


# The tables whose rows may hold a platform's raw ids (a worker's, a submission's, a study's):
# rewritten on PostgreSQL after an erasure or a scrub. Small: a row or a few per participant
# (tests/app/rights/test_forget_removed.py checks that every table with such a column is here).
PLATFORM_ID_TABLES = (
    "participants",
    "reviews",
    "bonuses",
    "messages",
    "mturk_replica_hits",
    "mturk_replica_assignments",
    "mturk_replica_submissions",
    "mturk_replica_bonuses",
    "prolific_replica_studies",
    "prolific_replica_submissions",
    "prolific_replica_bonus_setups",
    "prolific_replica_payments",
    "prolific_replica_messages",
    "prolific_replica_group_members",
)


class SecondServer(RuntimeError):
    """Another server already serves this SQLite file."""


class SingleServerLock:
    """The lock a server holds on its SQLite file while it serves (``<file>.server-lock``,
    an exclusive ``flock``, which the system releases when the process ends, also by a
    crash): SQLite's study has one server, and a second on the same file is refused at start.
    Several servers share a PostgreSQL database instead (docs/deployment.md)."""

    def __init__(self, url: str) -> None:
        parsed = make_url(url)
        self.path = Path(f"{parsed.database}.server-lock")
        self._file: Any = None

    def acquire(self) -> None:
        """Raises ``SecondServer`` where another server holds the file."""
        import fcntl

        handle = open(self.path, "a+")
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.close()
            raise SecondServer(
                f"another server already serves the SQLite database {self.path.name[:-12]} "
                f"(it holds {self.path}): a SQLite study has one server. To run several "
                "servers on one study, use PostgreSQL (BAM_DATABASE_URL=postgresql+psycopg://"
                "...; docs/deployment.md)"
            ) from None
        handle.seek(0)
        handle.truncate()
        handle.write(f"{os.getpid()}\n")
        handle.flush()
        self._file = handle

    def release(self) -> None:
        if self._file is not None:
            self._file.close()  # closing the file releases the lock
            self._file = None


def single_server_lock(url: str) -> SingleServerLock | None:
    """The lock a server on ``url`` must hold (SQLite), or None (PostgreSQL: several may)."""
    return SingleServerLock(url) if make_url(url).get_backend_name() == "sqlite" else None


def open_study_database(url: str) -> Database:
    """The study database at ``url``, to read from (the export, the analysis).

    A SQLite file is opened read-only: SQLite would create an empty database for a path that
    does not exist, and a reader never writes to (or changes the journal mode of) a study.
    Raises ``FileNotFoundError`` or ``ValueError`` (a bad URL) with a message that names no
    password.
    """
    try:
        parsed = make_url(url)
    except ArgumentError as error:
        raise ValueError(f"{url!r} is not a database URL: {error}") from None
    if parsed.get_backend_name() != "sqlite":
        return Database.from_url(url)
    if not parsed.database or parsed.database == ":memory:":
        raise ValueError("a SQLite URL needs the database file")
    file = Path(parsed.database)
    if not file.is_file():
        raise FileNotFoundError(f"no database file {file}")
    path = quote(file.resolve().as_posix())
    return Database(create_engine(f"sqlite:///file:{path}?mode=ro&uri=true"), read_only=True)


# -- migrations ------------------------------------------------------------------------------
def alembic_config(url: str | None = None) -> Any:
    from alembic.config import Config

    if not ALEMBIC_INI.is_file():
        raise SchemaError(
            f"{ALEMBIC_INI} is missing: run the server from its source tree "
            "(pip install -e .) or the Docker image"
        )
    config = Config(str(ALEMBIC_INI))
    config.set_main_option("script_location", str(MIGRATIONS))
    if url is not None:
        config.attributes["database_url"] = url
    return config


def head_revision() -> str:
    from alembic.script import ScriptDirectory

    head = ScriptDirectory.from_config(alembic_config()).get_current_head()
    if head is None:
        raise SchemaError(f"no migrations found in {MIGRATIONS}")
    return head


def current_revision(engine: Engine) -> str | None:
    from alembic.runtime.migration import MigrationContext

    with engine.connect() as connection:
        return MigrationContext.configure(connection).get_current_revision()


@contextmanager
def migration_connection(engine: Engine) -> Iterator[Connection]:
    """A connection in a transaction for the migrations. On SQLite, foreign keys are off while
    they run and checked before the commit, SQLite's own way to change a table that others
    refer to: a migration's batch copies the table and drops the original, which with foreign
    keys on would drop it under the rows that refer to it (``PRAGMA foreign_keys`` does nothing
    inside a transaction, so it is set before the transaction begins)."""
    with engine.connect() as connection:
        sqlite = engine.dialect.name == "sqlite"

        def foreign_keys(on: bool) -> None:
            cursor = connection.connection.cursor()  # the driver's: no transaction begun
            cursor.execute(f"PRAGMA foreign_keys={'ON' if on else 'OFF'}")
            cursor.close()

        if sqlite:
            foreign_keys(False)
        try:
            with connection.begin():
                yield connection
                if sqlite:
                    broken = connection.exec_driver_sql("PRAGMA foreign_key_check").all()
                    if broken:
                        raise SchemaError(
                            f"the migration left {len(broken)} rows whose foreign key refers "
                            f"to no row, e.g. {tuple(broken[0])}: nothing was changed"
                        )
        finally:
            if sqlite:
                foreign_keys(True)


def upgrade(engine: Engine, revision: str = "head") -> None:
    """Apply the migrations up to ``revision`` on the engine's database."""
    from alembic import command

    config = alembic_config()
    with migration_connection(engine) as connection:
        config.attributes["connection"] = connection
        command.upgrade(config, revision)


def downgrade(engine: Engine, revision: str) -> None:
    from alembic import command

    config = alembic_config()
    with migration_connection(engine) as connection:
        config.attributes["connection"] = connection
        command.downgrade(config, revision)


def prepare_schema(engine: Engine) -> str:
    """Bring the schema up to date before serving: migrate SQLite, check PostgreSQL.

    Returns what was done; raises ``SchemaError`` with the command to run otherwise.
    """
    head = head_revision()
    current = current_revision(engine)
    if current == head:
        return f"database schema is up to date ({head})"
    if engine.dialect.name == "sqlite":
        upgrade(engine)
        return f"database schema upgraded from {current or 'empty'} to {head}"
    url = engine.url.render_as_string(hide_password=True)
    raise SchemaError(
        f"the database schema at {url} is at revision {current or 'none (empty database)'}, "
        f"this server needs {head}: run `bam-study db upgrade` first (with BAM_DATABASE_URL "
        "set), after a backup"
    )
