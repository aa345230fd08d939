"""The request transaction: ``perform`` runs a request that changes something in one write
transaction. It checks the participant's token and the request's sequence number, lets the
handler change the state, and stores the event with the response it answers, so that a
retried request is answered identically and stored once.

The request path works on ``records.Record`` rows with SQLAlchemy Core (see ``storage/records.py``).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

import numpy as np
from sqlalchemy import Connection, bindparam, select

from server.app import platform_registry as registry
from server.app.errors import ApiError
from server.app.participants.statuses import reactivate
from server.app.participants.tokens import participant_for
from server.app.schemas import (
    SeqRequest,
)
from server.app.settings import Settings
from server.app.state import ServerState
from server.app.storage.models import (
    utcnow,
)
from server.app.storage.records import Record, add
from server.app.storage.tables import EVENTS, UPDATES
from server.app.storage.vocabulary import ParticipantStatus, UpdateStatus
from server.app.study_file import StudyConfig

# Prepared: the event a retried request's sequence number stored.
STORED_EVENT = select(EVENTS.c.request_hash, EVENTS.c.response).where(
    EVENTS.c.participant_id == bindparam("participant_id"), EVENTS.c.seq == bindparam("seq")
)


class LazyGenerator:
    """A NumPy generator made on first use: most requests draw nothing (the dynamics of every
    environment here are deterministic), and making one costs more than the rest of a move."""

    def __init__(self, seed: list[int]) -> None:
        self._seed = seed
        self._generator: np.random.Generator | None = None

    def __getattr__(self, name: str) -> Any:
        if self._generator is None:
            self._generator = np.random.default_rng(self._seed)
        return getattr(self._generator, name)


@dataclass
class QueuedUpdate:
    session_id: int
    update_index: int
    episodes: int
    actions: int


@dataclass
class Transaction:
    """One request being performed (see ``perform``)."""

    c: Connection
    participant: Record
    event: dict[str, Any]  # the event's columns, inserted after the handler
    server: ServerState
    now: datetime
    updates: list[QueuedUpdate] = field(default_factory=list)  # learner updates to queue
    records: list[Record] = field(default_factory=list)  # rows to write back

    def track(self, record: Record) -> Record:
        """Write this row's changes back when the request is done."""
        self.records.append(record)
        return record

    def flush(self) -> None:
        """Write the changes so far (before a query that must see them)."""
        self.participant.save(self.c)
        for record in self.records:
            record.save(self.c)

    @property
    def study(self) -> StudyConfig:
        return self.server.study

    @property
    def settings(self) -> Settings:
        return self.server.settings

    @property
    def seq(self) -> int:
        return int(self.event["seq"])

    def rng(self, seed: int) -> Any:
        """Randomness of this request, reproducible from the session's seed and the seq."""
        return LazyGenerator([seed, self.seq])

    def queue_update(self, session: Record) -> int:
        """Queue the session's next learner update (index ``updates_requested``), which will
        include this request's event."""
        self.updates.append(
            QueuedUpdate(session.id, session.updates_requested, session.episodes, session.actions)
        )
        return int(session.updates_requested)


def request_fingerprint(kind: str, session_id: int | None, body: SeqRequest) -> str:
    text = json.dumps(
        {"kind": kind, "session": session_id, "body": body.model_dump(mode="json")},
        sort_keys=True,
    )
    return hashlib.sha256(text.encode()).hexdigest()


@dataclass
class Performed:
    response: str  # the JSON answered (stored with the event)
    queued: list[int]  # sessions with newly queued learner updates


def perform(
    server: ServerState,
    token: str | None,
    kind: str,
    body: SeqRequest,
    handler: Callable[[Transaction], Any],
    session_id: int | None = None,
) -> Performed:
    """Run ``handler`` for this request in one transaction with its event (module docstring).

    The handler returns a Pydantic response model; an ``ApiError`` it raises rolls everything
    back, so a refused request changes nothing and does not use up its sequence number.
    """
    fingerprint = request_fingerprint(kind, session_id, body)
    db = server.db
    with db.transaction() as c:
        participant = participant_for(c, token, lock=not db.is_sqlite)
        if body.seq != participant.next_seq:
            if body.seq < participant.next_seq:
                stored = c.execute(
                    STORED_EVENT, {"participant_id": participant.id, "seq": body.seq}
                ).first()
                if stored is not None and stored.request_hash == fingerprint:
                    return Performed(stored.response, [])
                raise ApiError(
                    409,
                    f"sequence number {body.seq} was already used by a different request; "
                    f"the next sequence number is {participant.next_seq}",
                )
            raise ApiError(
                409,
                f"request out of order: sequence number {body.seq}, but the next is "
                f"{participant.next_seq} (an earlier request has not arrived)",
            )
        released = registry.platform(participant.platform).released
        if participant.status == ParticipantStatus.RETURNED and released is not None:
            raise ApiError(409, released.detail)
        if participant.status == ParticipantStatus.RETURNED:
            raise ApiError(
                409,
                "this task was returned (its assignment may have gone to another worker); "
                "to take part, accept the task again",
            )
        now = utcnow()
        reactivate(c, participant, now)
        event: dict[str, Any] = {
            "participant_id": participant.id,
            "session_id": session_id,
            "seq": body.seq,
            "kind": kind,
            "created_at": now,
            "request_hash": fingerprint,
        }
        participant.next_seq = body.seq + 1
        participant.last_seen_at = now
        transaction = Transaction(c, participant, event, server, now)
        response = handler(transaction).model_dump_json()
        event_id = add(c, EVENTS, response=response, **event)
        transaction.flush()
        for queued in transaction.updates:
            add(
                c,
                UPDATES,
                session_id=queued.session_id,
                update_index=queued.update_index,
                status=UpdateStatus.PENDING,
                through_event_id=event_id,
                episodes=queued.episodes,
                actions=queued.actions,
                queued_at=now,
            )
    return Performed(response, [queued.session_id for queued in transaction.updates])


# -- consent, sessions and completion ---------------------------------------------------------
