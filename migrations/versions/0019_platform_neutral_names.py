"""One name for each idea: a participant's ids on their platform, in the study's own tables, are
named for what they are on any platform rather than in MTurk's words, and the table of reviews
is named as the export names it.

- ``worker_id`` (MTurk's workerId, Prolific's PROLIFIC_PID) -> ``platform_participant_id``,
  ``assignment_id`` (MTurk's assignmentId, Prolific's SESSION_ID) -> ``platform_submission_id``
  and ``hit_id`` (MTurk's hitId, Prolific's STUDY_ID) -> ``platform_study_id``, in
  ``participants``, ``reviews``, ``bonuses`` and ``messages``; the erasures' pseudonyms of the
  first two -> ``platform_participant_pseudonym`` and ``platform_submission_pseudonym``;
- ``assignment_reviews`` -> ``reviews`` (and the erasures' count of its rows with it);
- the indexes and constraints named after them renamed with them.

The replicas' tables (``mturk_replica_*``, ``prolific_replica_*``) keep the platforms' own words.
Every row is kept, going up and coming back down. On SQLite the tables are copied (a batch), so
the migrations run with foreign keys off and checked before they commit
(``storage.db.migration_connection``): a copy of ``participants`` drops the table under the rows
that refer to it.

Revision ID: 0019
Revises: 0018
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op
from alembic.operations import BatchOperations

revision: str = "0019"
down_revision: str | None = "0018"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

PARTICIPANT, SUBMISSION, STUDY = (
    "platform_participant_id",
    "platform_submission_id",
    "platform_study_id",
)
# (table, former column, column) for each column renamed, in the study's own tables.
COLUMNS = (
    ("participants", "worker_id", PARTICIPANT),
    ("participants", "assignment_id", SUBMISSION),
    ("participants", "hit_id", STUDY),
    ("reviews", "assignment_id", SUBMISSION),
    ("reviews", "worker_id", PARTICIPANT),
    ("bonuses", "assignment_id", SUBMISSION),
    ("bonuses", "worker_id", PARTICIPANT),
    ("messages", "worker_id", PARTICIPANT),
    ("erasures", "worker_pseudonym", "platform_participant_pseudonym"),
    ("erasures", "assignment_pseudonym", "platform_submission_pseudonym"),
)
TYPES = {
    "participants": sa.String(length=128),
    "reviews": sa.String(length=128),
    "bonuses": sa.String(length=128),
    "messages": sa.String(length=128),
    "erasures": sa.String(length=32),
}
NULLABLE = {"participants": True, "erasures": True}


def _rename_columns(table: str, batch: BatchOperations, up: bool) -> None:
    for name, former, column in COLUMNS:
        if name == table:
            batch.alter_column(
                former if up else column,
                new_column_name=column if up else former,
                existing_type=TYPES[table],
                existing_nullable=NULLABLE.get(table, False),
            )


def _participants(up: bool) -> None:
    """The three ids, their unique constraint (named: the naming convention's name would be
    longer than PostgreSQL's 63 characters) and the index of the participant's id."""
    names = {
        True: (PARTICIPANT, SUBMISSION, "uq_participants_platform_ids"),
        False: ("worker_id", "assignment_id", "uq_participants_platform_worker_id_assignment_id"),
    }
    participant, submission, unique = names[up]
    _, _, old_unique = names[not up]
    # Two batches: a batch's copy cannot build a constraint on a column it renames.
    with op.batch_alter_table("participants") as batch:
        batch.drop_constraint(old_unique, type_="unique")
        batch.drop_index(f"ix_participants_{names[not up][0]}")
        _rename_columns("participants", batch, up)
    with op.batch_alter_table("participants") as batch:
        batch.create_unique_constraint(unique, ["platform", participant, submission])
    op.create_index(f"ix_participants_{participant}", "participants", [participant])


def _reviews(up: bool) -> None:
    """The table ``reviews`` (after its rename going up, before it coming down): its columns
    and the names of its constraints, which name the table and its columns."""
    names = {True: ("reviews", SUBMISSION), False: ("assignment_reviews", "assignment_id")}
    table, submission = names[up]
    old_table, old_submission = names[not up]
    with op.batch_alter_table("reviews") as batch:
        batch.drop_constraint(f"uq_{old_table}_{old_submission}", type_="unique")
        batch.drop_constraint(f"uq_{old_table}_participant_id", type_="unique")
        batch.drop_constraint(f"fk_{old_table}_participant_id_participants", type_="foreignkey")
        batch.drop_constraint(f"pk_{old_table}", type_="primary")
        _rename_columns("reviews", batch, up)
    with op.batch_alter_table("reviews") as batch:  # two batches, as for participants
        batch.create_primary_key(f"pk_{table}", ["id"])
        batch.create_unique_constraint(f"uq_{table}_{submission}", [submission])
        batch.create_unique_constraint(f"uq_{table}_participant_id", ["participant_id"])
        batch.create_foreign_key(
            f"fk_{table}_participant_id_participants", "participants", ["participant_id"], ["id"]
        )


def _rename_reviews_table(up: bool) -> None:
    old, new = ("assignment_reviews", "reviews") if up else ("reviews", "assignment_reviews")
    op.rename_table(old, new)
    if op.get_bind().dialect.name == "postgresql":  # the id's sequence follows its table
        op.execute(f"ALTER SEQUENCE {old}_id_seq RENAME TO {new}_id_seq")


def _erasures(up: bool) -> None:
    """The pseudonyms' columns, and each erasure's count of rows per table (``rows``), keyed by
    the table's name."""
    old, new = ("assignment_reviews", "reviews") if up else ("reviews", "assignment_reviews")
    erasures = sa.table("erasures", sa.column("id", sa.Integer), sa.column("rows", sa.JSON))
    bind = op.get_bind()
    for row_id, rows in bind.execute(sa.select(erasures.c.id, erasures.c.rows)).all():
        if isinstance(rows, dict) and old in rows:
            renamed = {(new if key == old else key): value for key, value in rows.items()}
            bind.execute(erasures.update().where(erasures.c.id == row_id).values(rows=renamed))
    with op.batch_alter_table("erasures") as batch:
        _rename_columns("erasures", batch, up)


def _columns(table: str, up: bool) -> None:
    with op.batch_alter_table(table) as batch:
        _rename_columns(table, batch, up)


def upgrade() -> None:
    _participants(up=True)
    _rename_reviews_table(up=True)
    _reviews(up=True)
    _columns("bonuses", up=True)
    _columns("messages", up=True)
    _erasures(up=True)


def downgrade() -> None:
    _erasures(up=False)
    _columns("messages", up=False)
    _columns("bonuses", up=False)
    _reviews(up=False)
    _rename_reviews_table(up=False)
    _participants(up=False)
