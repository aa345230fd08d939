"""Pseudonyms: a platform id replaced by a salted hash (HMAC-SHA256), the same wherever it is
written. The export writes them (``export.tables``), erasure keeps them in its audit row
(``rights.erasure``) and scrubbing writes them into the database itself (``rights.scrub``); a
scrubbed participant's ids are their pseudonyms already.

The key is ``BAM_SECRET`` when set, else the random secret created with the database
(``installations.secret``).
"""

from __future__ import annotations

import hashlib
import hmac
from typing import Any, Protocol

from sqlalchemy import select

from server.app.storage.db import Database
from server.app.storage.models import Installation

# The prefixes that say which id a pseudonym stands for.
WORKER = "w"  # MTurk workerId, Prolific PROLIFIC_PID
ASSIGNMENT = "a"  # MTurk assignmentId, Prolific SESSION_ID
COMPLETION_CODE = "c"


class _Reads(Protocol):
    def scalar(self, statement: Any) -> Any: ...


def pseudonym(secret: str, value: str | None, prefix: str) -> str | None:
    """``prefix`` + "_" + the first 16 hex digits of the value's HMAC-SHA256 (None for None)."""
    if value is None:
        return None
    digest = hmac.new(secret.encode(), value.encode(), hashlib.sha256).hexdigest()
    return f"{prefix}_{digest[:16]}"


def installation_secret(c: _Reads, configured: str | None = None) -> str:
    """The pseudonyms' key: ``configured`` (``BAM_SECRET``) when set, else the database's own
    secret, read through ``c`` (a connection or a session)."""
    if configured:
        return configured
    secret = c.scalar(select(Installation.secret).where(Installation.id == 1))
    if not secret:
        raise RuntimeError("the database has no installation secret: run `bam-study db upgrade`")
    return str(secret)


def database_secret(db: Database) -> str:
    """The database's own secret (``installation_secret`` in a read transaction of its own)."""
    with db.read() as s:
        return installation_secret(s)


def platform_pseudonyms(
    secret: str,
    platform_participant_id: str | None,
    platform_submission_id: str | None,
    scrubbed: bool = False,
) -> tuple[str | None, str | None]:
    """The worker and assignment pseudonyms of these ids; ``scrubbed``: the ids are pseudonyms
    already, and are returned as they are."""
    if scrubbed:
        return platform_participant_id, platform_submission_id
    return pseudonym(secret, platform_participant_id, WORKER), pseudonym(
        secret, platform_submission_id, ASSIGNMENT
    )


def participant_pseudonyms(participant: Any, secret: str) -> tuple[str | None, str | None]:
    """The participant's worker and assignment pseudonyms, as the export writes them."""
    return platform_pseudonyms(
        secret,
        participant.platform_participant_id,
        participant.platform_submission_id,
        participant.identifiers_scrubbed_at is not None,
    )
