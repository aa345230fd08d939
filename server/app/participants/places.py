"""Places in the study: how many participants are in it at once, and the line beyond.

At most ``max_active_participants`` (the study file; default: the capacity the server
measured, ``server.app.updates.capacity``) participants are in the study at once: arrived and
not yet finished (``vocabulary.IN_PROGRESS``), seen in the last ``BAM_ACTIVE_MINUTES``. A new
arrival beyond it is stored with the status ``waiting`` and sees the waiting page, which asks
for a place (``admit``) every few seconds; the first in line goes in as soon as a place frees.
A waiting participant has no domain yet (it is drawn at consent), so the balanced assignment
does not count them, and is never marked abandoned (only participants in the study are). One
whose page has not asked for a place for ``LINE_SECONDS`` has left the line: those behind go
ahead; back, they take their turn again.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Literal

from sqlalchemy import Connection, and_, func, select

from server.app.participants.arrival import Room
from server.app.participants.statuses import set_status
from server.app.schemas import QueueView
from server.app.state import ServerState
from server.app.storage.db import Database, advisory_lock_key
from server.app.storage.models import utcnow
from server.app.storage.records import load
from server.app.storage.tables import PARTICIPANTS, UPDATES
from server.app.storage.vocabulary import IN_PROGRESS, ParticipantStatus, UpdateStatus
from server.app.updates.queue import QueueState

LINE_SECONDS = 60.0  # a waiting page asks every few seconds: silent this long, it was closed
ASK_SECONDS = 3  # how often the waiting page asks (also its Retry-After)
_LOCK = select(func.pg_advisory_xact_lock(advisory_lock_key("bam-study places")))


@dataclass(frozen=True)
class Place:
    admitted: bool
    ahead: int  # waiting participants before this one
    active: int  # participants in the study
    limit: int | None  # participants in the study at once (None: no limit)


def study_limit(state: ServerState) -> int | None:
    """Participants in the study at once: the study file's, or the measured capacity (the
    whole deployment's, with several servers)."""
    if state.study.max_active_participants is not None:
        return state.study.max_active_participants
    capacity = state.updates.deployment_capacity() if state.updates is not None else None
    return capacity.participants if capacity is not None else None


def room_for(state: ServerState) -> Room:
    """For ``flow.arrive``: has a new participant a place now?"""
    limit = study_limit(state)
    active_minutes = state.settings.active_minutes
    return lambda c, now: has_room(c, now, limit, active_minutes)


def lock_places(c: Connection) -> None:
    """The rest of this transaction is the only one counting places (SQLite: its write
    transaction already excludes every other writer)."""
    if c.dialect.name == "postgresql":
        c.execute(_LOCK)


def active_count(c: Connection, now: datetime, active_minutes: float) -> int:
    """Participants in the study: in progress and seen in the last ``active_minutes``."""
    p = PARTICIPANTS.c
    since = now - timedelta(minutes=active_minutes)
    query = select(func.count()).where(p.status.in_(IN_PROGRESS), p.last_seen_at >= since)
    return int(c.scalar(query) or 0)


def waiting_count(c: Connection, now: datetime, before: int | None = None) -> int:
    """Participants in the line (their page asked in the last ``LINE_SECONDS``), those that
    arrived before participant ``before`` only if given."""
    p = PARTICIPANTS.c
    since = now - timedelta(seconds=LINE_SECONDS)
    condition = and_(p.status == ParticipantStatus.WAITING, p.last_seen_at >= since)
    if before is not None:
        condition = and_(condition, p.id < before)
    return int(c.scalar(select(func.count()).where(condition)) or 0)


def has_room(c: Connection, now: datetime, limit: int | None, active_minutes: float) -> bool:
    """In an arrival's write transaction: may a new participant go in now (no one waiting before
    them and a place free)? Holds the places until the transaction ends."""
    if limit is None:
        return True
    lock_places(c)
    return active_count(c, now, active_minutes) + waiting_count(c, now) < limit


def admit(db: Database, participant_id: int, limit: int | None, active_minutes: float) -> Place:
    """A waiting participant asks for a place: in if one is free for them (every one before
    them in line fits too), else stays in line, seen now."""
    now = utcnow()
    with db.transaction() as c:
        lock_places(c)
        current = load(c, PARTICIPANTS, PARTICIPANTS.c.id == participant_id)
        assert current is not None
        active = active_count(c, now, active_minutes)
        if current.status != ParticipantStatus.WAITING:
            return Place(True, 0, active, limit)
        ahead = waiting_count(c, now, before=int(current.id))
        admitted = limit is None or active + ahead < limit
        current.last_seen_at = now
        if admitted:
            set_status(c, current, ParticipantStatus.ARRIVED, now, note="a place freed")
        current.save(c)
        return Place(admitted, 0 if admitted else ahead, active + int(admitted), limit)


def queue_view(state: ServerState, queue: QueueState | None) -> QueueView:
    """The dashboard's live queue beside the capacity and the limit; ``queue``: the update
    manager's, read on its event loop."""
    manager = state.updates
    capacity = manager.deployment_capacity() if manager is not None else None
    longest = capacity.longest_update if capacity is not None else None
    now = utcnow()
    with state.db.connect() as c:
        active = active_count(c, now, state.settings.active_minutes)
        waiting = waiting_count(c, now)
        pending = int(
            c.scalar(select(func.count()).where(UPDATES.c.status == UpdateStatus.PENDING)) or 0
        )
    limit_from: Literal["study file", "capacity"] | None = None
    if state.study.max_active_participants is not None:
        limit_from = "study file"
    elif capacity is not None:
        limit_from = "capacity"
    return QueueView(
        capacity=capacity.participants if capacity is not None else None,
        update_seconds=round(capacity.update_seconds, 4) if capacity is not None else None,
        measured_on=capacity.measured_on if capacity is not None else None,
        server_seconds_per_update=(
            round(capacity.server_seconds, 4)
            if capacity is not None and capacity.server_seconds is not None
            else None
        ),
        longest_update_seconds=round(longest.seconds, 4) if longest is not None else None,
        longest_update_of=f"{longest.learner} in {longest.environment}" if longest else None,
        slots=capacity.slots if capacity is not None else manager.slots if manager else 0,
        update_interval_seconds=state.settings.update_interval_seconds,
        limit=study_limit(state),
        limit_from=limit_from,
        participants_active=active,
        participants_waiting=waiting,
        updates_pending=pending,
        sessions_updating=queue.sessions_updating if queue is not None else 0,
        sessions_awaited=queue.sessions_awaited if queue is not None else 0,
        oldest_wait_seconds=round(queue.oldest_wait_seconds, 1) if queue is not None else 0.0,
        updates_done=queue.completed if queue is not None else 0,
    )
