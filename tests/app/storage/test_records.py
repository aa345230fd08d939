"""The request path's prepared statements run on the driver's cursor (``storage/records.py``):
they must read and write exactly what SQLAlchemy's own execution does, on SQLite and on
PostgreSQL, fill in the same column defaults, and fail with SQLAlchemy's errors."""

from __future__ import annotations

import hashlib
from datetime import UTC, datetime
from typing import Any

import pytest
from sqlalchemy import Connection, Table, bindparam, insert, select
from sqlalchemy.exc import IntegrityError, InvalidRequestError

from server.app.participants.tokens import participant_by_token
from server.app.storage.db import Database
from server.app.storage.records import add, fetch_one, get
from server.app.storage.tables import EVENTS, PARTICIPANTS, SESSIONS, UPDATES

WHEN = datetime(2026, 11, 27, 13, 45, 6, 123456, tzinfo=UTC)
SESSION = {
    "kind": "study",
    "domain": "navigation",
    "environment": "doorway",
    "learner": "bam",
    "colour_name": "orange",
    "colour_hex": "#E69F00",
    "seed": 2**40 + 7,
}


def read(c: Connection, table: Table, row_id: int) -> dict[str, Any]:
    """The row as SQLAlchemy's own execution reads it."""
    row = c.execute(select(table).where(table.c.id == row_id)).mappings().one()
    return dict(row)


def new_participant(c: Connection, token_hash: str = "a" * 64, **values: Any) -> int:
    return add(c, PARTICIPANTS, token_hash=token_hash, platform="lab", status="teaching", **values)


def new_session(c: Connection, participant_id: int, **values: Any) -> int:
    return add(c, SESSIONS, participant_id=participant_id, ordinal=0, **SESSION, **values)


def test_rows_read_as_sqlalchemy_reads_them(db: Database) -> None:
    with db.transaction() as c:
        participant_id = new_participant(c, excluded_at=WHEN, platform_participant_id="W1")
        session_id = new_session(c, participant_id, demonstrated=[3, 0, 5], completed=True)
        event_id = add(
            c,
            EVENTS,
            participant_id=participant_id,
            session_id=session_id,
            seq=1,
            kind="move",
            created_at=WHEN,
            request_hash="f" * 64,
            response='{"ok": true}',
        )
        update_id = add(c, UPDATES, session_id=session_id, update_index=1, episodes=1, actions=4)
    with db.transaction() as c:
        for table, row_id in (
            (PARTICIPANTS, participant_id),
            (SESSIONS, session_id),
            (EVENTS, event_id),
            (UPDATES, update_id),
        ):
            record = get(c, table, row_id)
            assert record is not None
            expected = read(c, table, row_id)
            assert {key: getattr(record, key) for key in expected} == expected
            assert {key: type(getattr(record, key)) for key in expected} == {
                key: type(value) for key, value in expected.items()
            }
        session = read(c, SESSIONS, session_id)
        assert session["demonstrated"] == [3, 0, 5]
        assert session["completed"] is True
        assert session["seed"] == 2**40 + 7
        assert read(c, PARTICIPANTS, participant_id)["excluded_at"] == WHEN
        assert read(c, EVENTS, event_id)["created_at"] == WHEN
        assert get(c, SESSIONS, session_id + 1000) is None


def test_inserts_take_the_column_defaults_as_sqlalchemy_does(db: Database) -> None:
    before = datetime.now(UTC)
    with db.transaction() as c:
        participant_id = new_participant(c)
        ours_id = add(c, SESSIONS, participant_id=participant_id, ordinal=0, **SESSION)
        theirs_id = c.execute(
            insert(SESSIONS).values(participant_id=participant_id, ordinal=1, **SESSION)
        ).inserted_primary_key[0]
    after = datetime.now(UTC)
    with db.transaction() as c:
        participant = read(c, PARTICIPANTS, participant_id)
        assert (participant["next_seq"], participant["tutorial_step"]) == (1, 0)
        for key in ("created_at", "last_seen_at"):
            assert before <= participant[key] <= after
        ours = read(c, SESSIONS, ours_id)
        theirs = read(c, SESSIONS, theirs_id)
        assert (ours.pop("ordinal"), theirs.pop("ordinal")) == (0, 1)
        assert ours.pop("id") != theirs.pop("id")
        assert ours == theirs
        assert (ours["demonstrated"], ours["updates_requested"]) == ([], -1)
        assert (ours["mode"], ours["completed"]) == ("idle", False)


def test_changed_columns_are_written_back_with_their_types(db: Database) -> None:
    with db.transaction() as c:
        participant_id = new_participant(c)
        session_id = new_session(c, participant_id)
    with db.transaction() as c:
        session = get(c, SESSIONS, session_id)
        assert session is not None
        session.demonstrated = [1, 2]
        session.finished_at = WHEN
        session.completed = True
        session.mode = "agent"
        session.save(c)
        participant = get(c, PARTICIPANTS, participant_id)
        assert participant is not None
        participant.next_seq = 42
        participant.excluded_at = None
        participant.save(c)
    with db.transaction() as c:
        stored = read(c, SESSIONS, session_id)
        assert (stored["demonstrated"], stored["finished_at"]) == ([1, 2], WHEN)
        assert (stored["completed"], stored["mode"]) == (True, "agent")
        assert read(c, PARTICIPANTS, participant_id)["next_seq"] == 42


def test_the_participant_is_found_by_token_hash_and_locked_on_postgresql(db: Database) -> None:
    token = "the participant's token"
    with db.transaction() as c:
        participant_id = new_participant(c, hashlib.sha256(token.encode()).hexdigest())
    with db.transaction() as c:
        found = participant_by_token(c, token, lock=not db.is_sqlite)
        assert found is not None and found.id == participant_id
        assert participant_by_token(c, "another token") is None


def test_a_broken_constraint_is_sqlalchemy_s_integrity_error_and_stores_nothing(
    db: Database,
) -> None:
    with db.transaction() as c:
        participant_id = new_participant(c)
        session_id = new_session(c, participant_id)
    event = {
        "participant_id": participant_id,
        "session_id": session_id,
        "seq": 1,
        "kind": "move",
        "request_hash": "f" * 64,
        "response": "{}",
    }
    with pytest.raises(IntegrityError), db.transaction() as c:
        add(c, EVENTS, **event)
        add(c, EVENTS, **event)  # the same (participant, seq) again
    with db.transaction() as c:
        assert c.execute(select(EVENTS.c.id)).all() == []
        assert read(c, SESSIONS, session_id)["participant_id"] == participant_id


def test_literal_values_missing_values_and_expanding_lists(db: Database) -> None:
    with db.transaction() as c:
        first = new_participant(c, "a" * 64)
        new_participant(c, "b" * 64)
        latest = select(PARTICIPANTS.c.id).order_by(PARTICIPANTS.c.id.desc()).limit(1)
        assert fetch_one(c, latest, {}) == {"id": first + 1}
        by_hash = select(PARTICIPANTS.c.id).where(
            PARTICIPANTS.c.token_hash == bindparam("token_hash")
        )
        assert fetch_one(c, by_hash, {"token_hash": "a" * 64}) == {"id": first}
        with pytest.raises(InvalidRequestError, match="token_hash"):
            fetch_one(c, by_hash, {})
        listed = select(PARTICIPANTS.c.id).where(
            PARTICIPANTS.c.id.in_(bindparam("ids", expanding=True))
        )
        with pytest.raises(ValueError, match="expanding"):
            fetch_one(c, listed, {"ids": [first]})


def test_writes_share_one_connection_on_sqlite_only_and_a_failed_one_leaves_it_clean(
    db: Database,
) -> None:
    """On SQLite the request path's writes, one at a time, run on one connection kept open; a
    transaction that fails is rolled back on it, and one invalidated is replaced. On PostgreSQL,
    where writes run side by side, each takes a connection of its own from the pool."""
    shared = db.is_sqlite
    with db.transaction() as c:
        first = c
        participant_id = new_participant(c)
    with pytest.raises(IntegrityError), db.transaction() as c:
        assert (c is first) == shared
        add(c, SESSIONS, participant_id=participant_id, ordinal=0, **SESSION)
        add(c, SESSIONS, participant_id=participant_id, ordinal=0, **SESSION)  # same ordinal
    with db.transaction() as c:
        assert (c is first) == shared
        # The failed transaction's first session was rolled back with it.
        assert c.execute(select(SESSIONS.c.id)).all() == []
    if shared:
        first.invalidate()  # as after a driver error that lost the connection
    with db.transaction() as c:
        assert c is not first
        assert c.execute(select(PARTICIPANTS.c.id)).scalars().all() == [participant_id]
