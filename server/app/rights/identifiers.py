"""The rows that hold one participant's data, and the rewriting of raw ids in text cells, that
erasure and scrubbing share: the study's own rows, found from the foreign keys that lead to the
participant (``study_rows``), and the rows of the local platform replicas (MTurk's and
Prolific's) that hold their turn (each platform's ``own_replica_rows`` and
``shared_replica_rows``).

The replicas stand in for the platforms, which keep their own records: erasure removes the
study's rows and leaves the replicas' (a participant erased here is still a submission on
Prolific and an assignment on MTurk); scrubbing replaces the ids in both once they expire.
"""

from __future__ import annotations

import re
from typing import Any

from sqlalchemy import JSON, Connection, MetaData, String, Table, Text, select, update

from server.app import platform_registry as registry
from server.app.storage.models import Base
from server.app.storage.tables import PARTICIPANTS


def study_rows(participant_id: int, metadata: MetaData = Base.metadata) -> list[tuple[Table, Any]]:
    """(table, condition) for every table whose rows lead to the participant by foreign keys
    (their ``participant_id``, or a learning session of theirs, and so on), children before
    parents: erasure deletes them in this order. A table added to the schema with such a key
    is found here without a word elsewhere. The participants row itself is not among them; the
    replicas' rows (``participant_id`` there is a platform's id) are not either."""
    participants = metadata.tables[PARTICIPANTS.name]
    conditions: dict[Table, Any] = {participants: participants.c.id == participant_id}
    for table in metadata.sorted_tables:  # parents before children
        if table is participants:
            continue
        keys = [key for key in table.foreign_keys if key.column.table in conditions]
        direct = [key for key in keys if key.column.table is participants]
        if direct:  # its own participant_id says whose a row is (events: not its session)
            conditions[table] = direct[0].parent == participant_id
        elif keys:
            key = min(keys, key=lambda key: key.parent.name)
            conditions[table] = key.parent.in_(
                select(key.column).where(conditions[key.column.table])
            )
    return [
        (table, conditions[table])
        for table in reversed(metadata.sorted_tables)
        if table in conditions and table is not participants
    ]


def own_replica_rows(participant: Any) -> list[tuple[Table, Any]]:
    """(table, condition) for the replica rows of the participant's turn alone, children before
    parents: scrubbing replaces their ids. ``participant`` is a participants row."""
    return registry.platform(participant.platform).own_replica_rows(participant)


def shared_replica_rows(participant: Any) -> list[tuple[Table, Any]]:
    """(table, condition) for replica rows that name the participant among others (a Prolific
    bonus set-up's CSV, one line per participant): scrubbing replaces the participant's ids
    in them, and keeps the others'."""
    return registry.platform(participant.platform).shared_replica_rows(participant)


def id_pattern(raw_ids: dict[str, str]) -> re.Pattern[str]:
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


def rewrite_ids(c: Connection, table: Table, where: Any, raw_ids: dict[str, str]) -> int:
    """Replace each raw id (a key of ``raw_ids``) by its value in every text cell of
    ``table``'s rows matching ``where``; returns how many rows changed."""
    columns = [c for c in table.columns if isinstance(c.type, String | Text | JSON)]
    if not columns or not raw_ids:
        return 0
    pattern = id_pattern(raw_ids)
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
