"""Participants' statuses and tokens: the tables a request reads, the token that names a
participant, and the status changes every part of the flow makes.
"""

from __future__ import annotations

import hashlib
import secrets
from datetime import datetime, timedelta

from sqlalchemy import Connection, bindparam, func, insert, select

from server.app.errors import ApiError
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import (
    AttentionCheck,
    Event,
    LearnerUpdate,
    LearningSession,
    Participant,
    ParticipantToken,
    QuestionnaireAnswer,
    StatusChange,
    utcnow,
)
from server.app.storage.records import Record, add, fetch_one, load_all, table_of

# Flow statuses, in order; "returned" (MTurk: the HIT was returned), "abandoned" (idle too long)
# and "declined" (no consent) end the flow; exclusion is a separate mark.
# "questionnaire": the post-study questionnaire is being answered (a study file with one).
FLOW_STATUSES = (
    "arrived",
    "consented",
    "tutorial",
    "teaching",
    "questionnaire",
    "completed",
    "submitted",
)
IN_PROGRESS = ("arrived", "consented", "tutorial", "teaching", "questionnaire")
# "waiting": arrived while the study was full, for a place (``places``); not yet in the flow.
STATUSES = ("waiting", *FLOW_STATUSES, "declined", "returned", "abandoned")
CODE_ALPHABET = "ABCDEFGHJKLMNPQRSTUVWXYZ23456789"
TOKEN_HEADER = "X-Participant-Token"

PARTICIPANTS = table_of(Participant)
SESSIONS = table_of(LearningSession)
EVENTS = table_of(Event)
UPDATES = table_of(LearnerUpdate)
STATUS_CHANGES = table_of(StatusChange)
TOKENS = table_of(ParticipantToken)
ANSWERS = table_of(QuestionnaireAnswer)
CHECKS = table_of(AttentionCheck)

SYSTEM_RANDOM = secrets.SystemRandom()
# Prepared: every request looks its participant up by token.
_BY_TOKEN = select(PARTICIPANTS).where(PARTICIPANTS.c.token_hash == bindparam("token_hash"))
_BY_TOKEN_LOCKED = _BY_TOKEN.with_for_update()
# A further browser's token (see ParticipantToken), looked up when the first's does not match.
_BY_FURTHER_TOKEN = select(PARTICIPANTS).where(
    PARTICIPANTS.c.id
    == select(TOKENS.c.participant_id)
    .where(TOKENS.c.token_hash == bindparam("token_hash"))
    .scalar_subquery()
)
_BY_FURTHER_TOKEN_LOCKED = _BY_FURTHER_TOKEN.with_for_update()
ADD_TOKEN = insert(TOKENS)


def advisory_lock_key(name: str) -> int:
    """A PostgreSQL advisory lock key: the first 8 bytes of sha256(name)."""
    return int.from_bytes(hashlib.sha256(name.encode()).digest()[:8], "big", signed=True)


DOMAIN_LOCK_KEY = advisory_lock_key("bam-study domain assignment")
LOCK_DOMAIN_ASSIGNMENT = select(func.pg_advisory_xact_lock(DOMAIN_LOCK_KEY))
STORED_EVENT = select(EVENTS.c.request_hash, EVENTS.c.response).where(
    EVENTS.c.participant_id == bindparam("participant_id"), EVENTS.c.seq == bindparam("seq")
)


# -- identity -------------------------------------------------------------------------------
def new_token() -> tuple[str, str]:
    token = secrets.token_urlsafe(32)
    return token, hash_token(token)


def hash_token(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def participant_by_token(c: Connection, token: str, lock: bool = False) -> Record | None:
    """The participant whose token (any of its browsers') this is; ``lock`` holds its row until
    the transaction ends (PostgreSQL; SQLite writes are serialised already)."""
    token_hash = {"token_hash": hash_token(token)}
    row = fetch_one(c, _BY_TOKEN_LOCKED if lock else _BY_TOKEN, token_hash)
    if row is None:
        further = _BY_FURTHER_TOKEN_LOCKED if lock else _BY_FURTHER_TOKEN
        row = fetch_one(c, further, token_hash)
    return None if row is None else Record(PARTICIPANTS, row)


def participant_for(c: Connection, token: str | None, lock: bool = False) -> Record:
    """The participant whose token this is (401 otherwise); ``lock`` as above."""
    if not token or len(token) > 128:
        raise ApiError(401, "no participant: open the study from its link again")
    participant = participant_by_token(c, token, lock)
    if participant is None:
        raise ApiError(401, "unknown participant token: open the study from its link again")
    return participant


# -- statuses -------------------------------------------------------------------------------
def set_status(
    c: Connection, participant: Record, status: str, now: datetime, note: str | None = None
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
    set_status(c, participant, previous or "arrived", now, note="came back")


def reactivate(c: Connection, participant: Record, now: datetime) -> None:
    """A participant marked abandoned who is active again continues where they were. (One whose
    MTurk assignment went to another worker continues only by arriving with it again.)"""
    if participant.status == "abandoned":
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
            set_status(c, participant, "abandoned", now, note=since)
            participant.save(c)
        return len(idle)


# -- arrival --------------------------------------------------------------------------------
