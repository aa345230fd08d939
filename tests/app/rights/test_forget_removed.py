"""An erasure or a scrub leaves no raw platform id in the database's files, not only in its
rows: SQLite's deleted content zeroed and its write-ahead log truncated, PostgreSQL's tables
that hold platform ids rewritten with their indexes (Database.forget_removed)."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest
from sqlalchemy import String, text

import server.app.storage.replica_models  # noqa: F401  (its tables are in the metadata)
from server.app.rights.erasure import erase_participant
from server.app.rights.scrub import scrub
from server.app.storage.db import PLATFORM_ID_TABLES, Database
from server.app.storage.models import Base, Participant
from tests.support.server import BOUND

ERASED = "ERASEDWORKER5f3a9c"  # a raw PROLIFIC_PID of an erased participant
SCRUBBED = "SCRUBBEDWORKER7d21e"  # one whose ids a scrub replaced by pseudonyms


def add_participants(db: Database) -> tuple[int, int]:
    with db.write() as s:
        rows = [
            Participant(
                token_hash=f"{number}" * 64,
                platform="prolific",
                status="submitted",
                platform_participant_id=worker,
                platform_submission_id=f"{worker}-SESSION",
                platform_study_id="STUDY1",
            )
            for number, worker in ((1, ERASED), (2, SCRUBBED))
        ]
        s.add_all(rows)
        s.flush()
        return rows[0].id, rows[1].id


def sqlite_bytes(db: Database) -> bytes:
    path = Path(str(db.engine.url.database))
    wal = path.with_name(path.name + "-wal")
    return path.read_bytes() + (wal.read_bytes() if wal.exists() else b"")


def postgresql_bytes(db: Database) -> bytes:
    """The files of the tables that hold platform ids and of all their indexes, after a
    checkpoint (what a copy of the data folder would hold)."""
    with db.engine.connect() as c:
        c.execute(text("CHECKPOINT"))
        data = Path(str(c.scalar(text("SHOW data_directory"))))
        if not os.access(data, os.R_OK | os.X_OK):
            pytest.skip(f"PostgreSQL's data folder {data} cannot be read by this user")
        relations = c.execute(
            text(
                "SELECT pg_relation_filepath(c.oid) FROM pg_class c "
                "JOIN pg_namespace n ON n.oid = c.relnamespace "
                "WHERE n.nspname = current_schema() AND c.relkind IN ('r', 'i', 't')"
            )
        ).scalars()
        files = [data / path for path in relations if path]
    content = b""
    for file in files:
        for segment in sorted(file.parent.glob(file.name + "*")):  # .1 segments, _fsm, _vm
            content += segment.read_bytes()
    return content


def test_an_erasure_and_a_scrub_leave_no_raw_id_in_the_files(db: Database) -> None:
    read = sqlite_bytes if db.is_sqlite else postgresql_bytes
    erased, _ = add_participants(db)
    before = read(db)
    assert ERASED.encode() in before and SCRUBBED.encode() in before  # the test can see them
    erase_participant(db, erased, "experimenter")
    assert scrub(db) == 1
    after = read(db)
    deadline = time.monotonic() + BOUND
    while not db.is_sqlite and (ERASED.encode() in after or SCRUBBED.encode() in after):
        # PostgreSQL keeps a replaced row while another client's open transaction (another
        # test's, on the same database server) may still see it; the next rewrite drops it.
        assert time.monotonic() < deadline, "a removed id stays in the files"
        time.sleep(0.5)
        db.forget_removed()
        after = read(db)
    assert ERASED.encode() not in after
    assert SCRUBBED.encode() not in after
    # The rows that remain are intact: the scrubbed participant, under pseudonyms.
    with db.read() as s:
        (left,) = s.query(Participant).all()
    assert left.platform_participant_id is not None and left.platform_participant_id != SCRUBBED


PLATFORM_ID_COLUMNS = ("platform_participant_id", "platform_submission_id", "platform_study_id")


def test_every_table_with_a_platform_id_column_is_rewritten_on_postgresql() -> None:
    holding = {
        table.name
        for table in Base.metadata.sorted_tables
        for column in table.columns
        # The study's names for a platform's ids, and the MTurk replica's (MTurk's words).
        if column.name in (*PLATFORM_ID_COLUMNS, "worker_id", "assignment_id", "hit_id")
        or (column.name == "participant_id" and isinstance(column.type, String))
    }
    assert holding <= set(PLATFORM_ID_TABLES)
