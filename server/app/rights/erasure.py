"""Erasing one participant: every row of theirs, in every table, in one transaction, and one
audit row (``erasures``) that says when, by whom, under which pseudonyms and how many rows each
table lost. The audit row holds no personal data: the pseudonyms are those of the export, so
that copies exported before can be cleaned.

Erasure is the one exception to the append-only event log (docs/guarantees.md).

The local platform replicas' rows (a Prolific submission, an MTurk assignment, their payments)
are the platform's record, not ours: Prolific and MTurk keep theirs when a study erases a
participant, so the replicas keep theirs too, under the platform's ids, and their status
changes only as the platform's would (a withdrawn Prolific participant's NO_CONSENT code
completes the submission with a return requested; returning it is theirs to do). Scrubbing
(``scrub``) still replaces the replicas' ids by pseudonyms once they expire.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import BaseModel, Field
from sqlalchemy import Connection, delete, select

from server.app.errors import ApiError
from server.app.rights.identifiers import study_rows
from server.app.rights.pseudonyms import (
    WORKER,
    installation_secret,
    participant_pseudonyms,
    pseudonym,
)
from server.app.storage.db import Database
from server.app.storage.models import Participant, utcnow
from server.app.storage.records import Record, add
from server.app.storage.tables import ERASURES, PARTICIPANTS
from server.app.storage.vocabulary import ErasedBy

ERASED_BY = tuple(ErasedBy)


class Erased(BaseModel):
    """What an erasure removed (the audit row's content)."""

    erasure_id: int
    participant_id: int
    platform: str
    platform_participant_pseudonym: str | None
    platform_submission_pseudonym: str | None
    rows: dict[str, int] = Field(description="Rows removed, per table.")


def find_participant(c: Connection, who: str, secret: str) -> Any:
    """The participant named by ``who``: a participant number, a worker id (MTurk workerId or
    Prolific PROLIFIC_PID) or its pseudonym (w_...). Raises ``ApiError`` 404 when none matches
    and 409 when several do (a worker with several participations: name it by number)."""
    p = PARTICIPANTS.c
    if who.isdigit() and len(who) <= 10:
        rows = c.execute(select(PARTICIPANTS).where(p.id == int(who))).mappings().all()
    else:
        # A raw id (scrubbed participants keep its pseudonym), or a scrubbed one's pseudonym.
        named = (who, pseudonym(secret, who, WORKER))
        rows = (
            c.execute(select(PARTICIPANTS).where(p.platform_participant_id.in_(named)))
            .mappings()
            .all()
        )
        if not rows and who.startswith("w_"):  # the pseudonym of a participant not scrubbed
            rows = [
                row
                for row in c.execute(
                    select(PARTICIPANTS).where(
                        p.platform_participant_id.is_not(None), p.identifiers_scrubbed_at.is_(None)
                    )
                ).mappings()
                if pseudonym(secret, row["platform_participant_id"], WORKER) == who
            ]
    if not rows:
        raise ApiError(
            404, f"no participant {who!r} (a participant number, worker id or w_ pseudonym)"
        )
    if len(rows) > 1:
        numbers = ", ".join(str(row["id"]) for row in rows)
        raise ApiError(
            409, f"{who!r} took part {len(rows)} times (participants {numbers}): name one by number"
        )
    return rows[0]


def erase(
    c: Connection, participant_id: int, by: ErasedBy, secret: str, now: datetime | None = None
) -> Erased:
    """Erase the participant ``participant_id`` in the transaction ``c`` (see the module
    docstring); ``by`` is ``participant`` or ``experimenter``. Raises ``ApiError`` 404 for an
    unknown participant (one erased already is unknown)."""
    if by not in ERASED_BY:
        raise ValueError(f"erased by {by!r}: one of {', '.join(ERASED_BY)}")
    now = now or utcnow()
    query = select(PARTICIPANTS).where(PARTICIPANTS.c.id == participant_id)
    if c.dialect.name == "postgresql":
        query = query.with_for_update()  # the participant's own requests wait, then find none
    participant = c.execute(query).mappings().first()
    if participant is None:
        raise ApiError(404, f"no participant {participant_id}")
    record = Record(PARTICIPANTS, participant)
    worker, assignment = participant_pseudonyms(record, secret)
    # Children before parents (foreign keys); each statement's count is the table's figure.
    statements: list[tuple[str, Any]] = [
        (table.name, delete(table).where(where)) for table, where in study_rows(participant_id)
    ]
    statements.append(("participants", delete(Participant).where(Participant.id == participant_id)))
    rows = {}
    for name, statement in statements:
        rows[name] = int(c.execute(statement.execution_options(synchronize_session=False)).rowcount)
    erasure_id = add(
        c,
        ERASURES,
        erased_at=now,
        erased_by=by,
        participant_id=participant_id,
        platform=participant["platform"],
        platform_participant_pseudonym=worker,
        platform_submission_pseudonym=assignment,
        rows=rows,
    )
    return Erased(
        erasure_id=erasure_id,
        participant_id=participant_id,
        platform=participant["platform"],
        platform_participant_pseudonym=worker,
        platform_submission_pseudonym=assignment,
        rows=rows,
    )


def erase_participant(
    db: Database, participant_id: int, by: ErasedBy, configured_secret: str | None = None
) -> Erased:
    """``erase`` in a write transaction of its own, then what it deleted out of the files."""
    with db.transaction() as c:
        erased = erase(c, participant_id, by, installation_secret(c, configured_secret))
    db.forget_removed()
    return erased
