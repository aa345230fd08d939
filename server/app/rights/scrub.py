"""Platform ids that expire: a participant's worker id (MTurk workerId, Prolific PROLIFIC_PID),
assignment id (MTurk assignmentId, Prolific SESSION_ID) and completion code are replaced by their
pseudonyms in the database itself, in every row of theirs that holds them (their participant
row, reviews, bonuses, stored responses, the platform replicas' rows), once they are no longer
needed to pay them: ``scrub_identifiers_after_days`` (study file) after their last request, or
on demand (``bam-study db scrub``).

The pseudonyms are the export's (``w_``, ``a_``, ``c_`` + salted hash), so the export and the
analysis read a scrubbed database as before; ``participants.identifiers_scrubbed_at`` marks the
participants whose ids are pseudonyms already.
"""

from __future__ import annotations

from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import Connection, select, update

from server.app.platform_registry import platforms
from server.app.rights.identifiers import (
    own_replica_rows,
    rewrite_ids,
    shared_replica_rows,
    study_rows,
)
from server.app.rights.pseudonyms import (
    ASSIGNMENT,
    COMPLETION_CODE,
    WORKER,
    installation_secret,
    pseudonym,
)
from server.app.storage.db import Database
from server.app.storage.models import utcnow
from server.app.storage.tables import PARTICIPANTS


def with_ids() -> list[str]:
    """The platforms whose participants have ids there (all but the lab)."""
    return [platform.name for platform in platforms() if platform.parameters]


def replacements(participant: Any, secret: str) -> dict[str, str]:
    """Raw id -> its pseudonym, for the participant's ids that are set."""
    pairs = (
        (participant.platform_participant_id, WORKER),
        (participant.platform_submission_id, ASSIGNMENT),
        (participant.completion_code, COMPLETION_CODE),
    )
    return {raw: str(pseudonym(secret, raw, prefix)) for raw, prefix in pairs if raw}


def scrub_participant(c: Connection, participant: Any, secret: str, now: datetime) -> None:
    """Replace the participant's raw ids by their pseudonyms everywhere (see the module
    docstring), in the transaction ``c``."""
    raw_ids = replacements(participant, secret)
    if raw_ids:
        for table, where in (
            study_rows(participant.id)
            + own_replica_rows(participant)
            + shared_replica_rows(participant)
        ):
            rewrite_ids(c, table, where, raw_ids)
        rewrite_ids(c, PARTICIPANTS, PARTICIPANTS.c.id == participant.id, raw_ids)
    c.execute(
        update(PARTICIPANTS)
        .where(PARTICIPANTS.c.id == participant.id)
        .values(identifiers_scrubbed_at=now)
    )


def scrub(
    db: Database,
    configured_secret: str | None = None,
    older_than_days: float | None = None,
    now: datetime | None = None,
) -> int:
    """Scrub the platform participants not scrubbed yet, all of them or those whose last
    request is more than ``older_than_days`` old; returns how many were scrubbed."""
    now = now or utcnow()
    p = PARTICIPANTS.c
    query = select(PARTICIPANTS).where(
        p.identifiers_scrubbed_at.is_(None), p.platform.in_(with_ids())
    )
    if older_than_days is not None:
        query = query.where(p.last_seen_at < now - timedelta(days=older_than_days))
    with db.transaction() as c:
        secret = installation_secret(c, configured_secret)
        participants = c.execute(query.order_by(p.id)).all()
        for participant in participants:
            scrub_participant(c, participant, secret, now)
    if participants:
        db.forget_removed()
    return len(participants)
