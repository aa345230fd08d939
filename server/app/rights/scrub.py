"""Platform ids that expire: a participant's worker id (MTurk workerId, Prolific PROLIFIC_PID),
assignment id (MTurk assignmentId, Prolific SESSION_ID) and completion code are replaced by their
pseudonyms in the database itself, in every row of theirs that holds them (their participant
row, reviews, bonuses, stored responses, the MTurk replica's rows), once they are no longer
needed to pay them: ``scrub_identifiers_after_days`` (study file) after their last request, or
on demand (``bam-study db scrub``).

The pseudonyms are the export's (``w_``, ``a_``, ``c_`` + salted hash), so the export and the
analysis read a scrubbed database as before; ``participants.identifiers_scrubbed_at`` marks the
participants whose ids are pseudonyms already.
"""

from __future__ import annotations

import re
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import JSON, Connection, String, Table, Text, and_, select, update

from server.app.export.tables import pseudonym
from server.app.rights.erasure import installation_secret
from server.app.storage.db import Database
from server.app.storage.models import Base, Participant, utcnow
from server.app.storage.records import table_of
from server.app.storage.replica_models import (
    ReplicaAssignment,
    ReplicaBonus,
    ReplicaSubmission,
)

PARTICIPANTS = table_of(Participant)
PLATFORMS = ("mturk", "prolific")
# The replica's rows of one worker's turn at one assignment.
REPLICA_TABLES = tuple(table_of(m) for m in (ReplicaAssignment, ReplicaSubmission, ReplicaBonus))


def replacements(participant: Any, secret: str) -> dict[str, str]:
    """Raw id -> its pseudonym, for the participant's ids that are set."""
    pairs = (
        (participant.worker_id, "w"),
        (participant.assignment_id, "a"),
        (participant.completion_code, "c"),
    )
    return {raw: str(pseudonym(secret, raw, prefix)) for raw, prefix in pairs if raw}


def _pattern(raw_ids: dict[str, str]) -> re.Pattern[str]:
    """The raw ids as whole tokens (ids are letters, digits, _ and -: a longer id that contains
    one is another id, left alone)."""
    alternatives = "|".join(re.escape(raw) for raw in sorted(raw_ids, key=len, reverse=True))
    return re.compile(rf"(?<![A-Za-z0-9_\-])(?:{alternatives})(?![A-Za-z0-9_\-])")


def _replaced(value: Any, pattern: re.Pattern[str], raw_ids: dict[str, str]) -> Any:
    if isinstance(value, str):
        return pattern.sub(lambda m: raw_ids[m.group(0)], value)
    if isinstance(value, dict):
        return {k: _replaced(v, pattern, raw_ids) for k, v in value.items()}
    if isinstance(value, list):
        return [_replaced(v, pattern, raw_ids) for v in value]
    return value


def _text_columns(table: Table) -> list[Any]:
    return [c for c in table.columns if isinstance(c.type, String | Text | JSON)]


def _rewrite(
    c: Connection, table: Table, where: Any, pattern: re.Pattern[str], raw_ids: dict[str, str]
) -> int:
    """Replace the raw ids in every text cell of ``table``'s rows matching ``where``."""
    columns = _text_columns(table)
    if not columns:
        return 0
    keys = list(table.primary_key.columns)
    changed = 0
    for row in c.execute(select(*keys, *columns).where(where)).mappings().all():
        values = {
            column.name: new
            for column in columns
            if (new := _replaced(row[column.name], pattern, raw_ids)) != row[column.name]
        }
        if values:
            c.execute(update(table).where(*(key == row[key.name] for key in keys)).values(values))
            changed += 1
    return changed


def scrub_participant(c: Connection, participant: Any, secret: str, now: datetime) -> None:
    """Replace the participant's raw ids by their pseudonyms everywhere (see the module
    docstring), in the transaction ``c``."""
    raw_ids = replacements(participant, secret)
    if raw_ids:
        pattern = _pattern(raw_ids)
        for table in Base.metadata.sorted_tables:
            if table is PARTICIPANTS:
                continue
            if "participant_id" in table.c:
                _rewrite(c, table, table.c.participant_id == participant.id, pattern, raw_ids)
        if participant.platform == "mturk" and participant.worker_id and participant.assignment_id:
            for table in REPLICA_TABLES:
                turn = and_(
                    table.c.worker_id == participant.worker_id,
                    table.c.assignment_id == participant.assignment_id,
                )
                _rewrite(c, table, turn, pattern, raw_ids)
        _rewrite(c, PARTICIPANTS, PARTICIPANTS.c.id == participant.id, pattern, raw_ids)
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
        p.identifiers_scrubbed_at.is_(None), p.platform.in_(PLATFORMS)
    )
    if older_than_days is not None:
        query = query.where(p.last_seen_at < now - timedelta(days=older_than_days))
    with db.transaction() as c:
        secret = installation_secret(c, configured_secret)
        participants = c.execute(query.order_by(p.id)).all()
        for participant in participants:
            scrub_participant(c, participant, secret, now)
    return len(participants)
