"""A participant's status changes: each one recorded in ``status_changes`` with its time, the
way back for one who returns, and the idle marked abandoned. The statuses themselves are
``ParticipantStatus`` (``storage.vocabulary``).
"""

from __future__ import annotations

from datetime import datetime, timedelta

from sqlalchemy import Connection, select

from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import utcnow
from server.app.storage.records import Record, add, load_all
from server.app.storage.tables import PARTICIPANTS, STATUS_CHANGES
from server.app.storage.vocabulary import FLOW_STATUSES, IN_PROGRESS, ParticipantStatus


def set_status(
    c: Connection,
    participant: Record,
    status: ParticipantStatus,
    now: datetime,
    note: str | None = None,
) -> None:
    participant.status = status
    add(c, STATUS_CHANGES, participant_id=participant.id, status=status, at=now, note=note)


def restore_status(c: Connection, participant: Record, now: datetime) -> None:
    """Back to the flow status the participant had before being marked abandoned or returned."""
    previous = c.scalar(
        select(STATUS_CHANGES.c.status)
        .where(
            STATUS_CHANGES.c.participant_id == participant.id,
            STATUS_CHANGES.c.status.in_(FLOW_STATUSES),
        )
        .order_by(STATUS_CHANGES.c.id.desc())
        .limit(1)
    )
    status = ParticipantStatus(previous) if previous else ParticipantStatus.ARRIVED
    set_status(c, participant, status, now, note="came back")


def reactivate(c: Connection, participant: Record, now: datetime) -> None:
    """A participant marked abandoned who is active again continues where they were. (One whose
    MTurk assignment went to another worker continues only by arriving with it again.)"""
    if participant.status == ParticipantStatus.ABANDONED:
        restore_status(c, participant, now)


def mark_abandoned(db: Database, settings: Settings) -> int:
    """Mark participants idle for longer than ``abandon_minutes`` as abandoned."""
    now = utcnow()
    cutoff = now - timedelta(minutes=settings.abandon_minutes)
    with db.transaction() as c:
        idle = load_all(
            c,
            PARTICIPANTS,
            PARTICIPANTS.c.status.in_(IN_PROGRESS),
            PARTICIPANTS.c.last_seen_at < cutoff,
        )
        for participant in idle:
            since = f"idle since {participant.last_seen_at:%Y-%m-%d %H:%M} UTC"
            set_status(c, participant, ParticipantStatus.ABANDONED, now, note=since)
            participant.save(c)
        return len(idle)
