"""Participants' tokens: the bearer token that names a participant on every request (its
SHA-256 is what the database keeps), and the completion codes they are given.
"""

from __future__ import annotations

import hashlib
import secrets

from sqlalchemy import Connection, bindparam, insert, select

from server.app.errors import ApiError
from server.app.storage.records import Record, fetch_one
from server.app.storage.tables import PARTICIPANTS, TOKENS

CODE_ALPHABET = "ABCDEFGHJKLMNPQRSTUVWXYZ23456789"
TOKEN_HEADER = "X-Participant-Token"

# The system's randomness: completion codes, and the assignment's draws without a seed.
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
