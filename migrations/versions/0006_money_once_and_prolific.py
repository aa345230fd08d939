"""Money exactly once: a decision and a bonus are recorded as an intent (``state`` pending)
before the platform is called and settled afterwards; a bonus keeps its currency and Prolific's
set-up id; a rejection keeps Prolific's category. Each participant's Prolific status, the Prolific webhook events applied,
and the local Prolific replica's tables.

Revision ID: 0006p
Revises: 0005
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0006p"
down_revision: str | None = "0005"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

When = sa.DateTime(timezone=True)


def upgrade() -> None:
    with op.batch_alter_table("assignment_reviews") as batch:
        batch.add_column(sa.Column("rejection_category", sa.String(length=32), nullable=True))
        batch.add_column(
            sa.Column("state", sa.String(length=16), nullable=False, server_default="done")
        )
        batch.add_column(sa.Column("requested_at", When, nullable=True))
        batch.alter_column("backend", type_=sa.String(length=24), existing_nullable=False)
        batch.alter_column("decided_at", existing_type=When, nullable=True)
    op.execute("UPDATE assignment_reviews SET requested_at = decided_at")
    with op.batch_alter_table("assignment_reviews") as batch:
        batch.alter_column("requested_at", existing_type=When, nullable=False)
        batch.alter_column("state", server_default=None, existing_type=sa.String(length=16))

    with op.batch_alter_table("bonuses") as batch:
        batch.add_column(
            sa.Column("currency", sa.String(length=3), nullable=False, server_default="USD")
        )
        batch.add_column(
            sa.Column("state", sa.String(length=16), nullable=False, server_default="paid")
        )
        batch.add_column(sa.Column("setup_id", sa.String(length=64), nullable=True))
        batch.add_column(sa.Column("requested_at", When, nullable=True))
        batch.alter_column("backend", type_=sa.String(length=24), existing_nullable=False)
        batch.alter_column("paid_at", existing_type=When, nullable=True)
    op.execute("UPDATE bonuses SET requested_at = paid_at")
    with op.batch_alter_table("bonuses") as batch:
        batch.alter_column("requested_at", existing_type=When, nullable=False)
        batch.alter_column("state", server_default=None, existing_type=sa.String(length=16))
        batch.alter_column("currency", server_default=None, existing_type=sa.String(length=3))

    with op.batch_alter_table("participants") as batch:
        batch.add_column(sa.Column("prolific_status", sa.String(length=24), nullable=True))
    op.create_table(
        "prolific_events",
        sa.Column("event_id", sa.String(length=128), nullable=False),
        sa.Column("event_type", sa.String(length=64), nullable=False),
        sa.Column("received_at", When, nullable=False),
        sa.PrimaryKeyConstraint("event_id", name=op.f("pk_prolific_events")),
    )
    op.create_table(
        "prolific_replica_studies",
        sa.Column("id", sa.String(length=24), nullable=False),
        sa.Column("name", sa.String(length=200), nullable=False),
        sa.Column("status", sa.String(length=24), nullable=False),
        sa.Column("external_study_url", sa.Text(), nullable=False),
        sa.Column("total_available_places", sa.Integer(), nullable=False),
        sa.Column("reward", sa.Integer(), nullable=False),
        sa.Column("maximum_allowed_time", sa.Integer(), nullable=False),
        sa.Column("fields", sa.JSON(), nullable=False),
        sa.Column("created_at", When, nullable=False),
        sa.Column("published_at", When, nullable=True),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_prolific_replica_studies")),
    )
    op.create_table(
        "prolific_replica_submissions",
        sa.Column("id", sa.String(length=24), nullable=False),
        sa.Column("study_id", sa.String(length=24), nullable=False),
        sa.Column("participant_id", sa.String(length=24), nullable=False),
        sa.Column("status", sa.String(length=24), nullable=False),
        sa.Column("started_at", When, nullable=False),
        sa.Column("completed_at", When, nullable=True),
        sa.Column("study_code", sa.String(length=64), nullable=True),
        sa.Column("rejection_category", sa.String(length=32), nullable=True),
        sa.Column("message", sa.Text(), nullable=True),
        sa.Column("reviewed_at", When, nullable=True),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_prolific_replica_submissions")),
    )
    op.create_index(
        op.f("ix_prolific_replica_submissions_study_id"),
        "prolific_replica_submissions",
        ["study_id"],
    )
    op.create_table(
        "prolific_replica_bonus_setups",
        sa.Column("id", sa.String(length=24), nullable=False),
        sa.Column("study_id", sa.String(length=24), nullable=False),
        sa.Column("csv_bonuses", sa.Text(), nullable=False),
        sa.Column("amount", sa.Integer(), nullable=False),
        sa.Column("created_at", When, nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_prolific_replica_bonus_setups")),
    )
    op.create_index(
        op.f("ix_prolific_replica_bonus_setups_study_id"),
        "prolific_replica_bonus_setups",
        ["study_id"],
    )
    op.create_table(
        "prolific_replica_payments",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("setup_id", sa.String(length=24), nullable=False),
        sa.Column("participant_id", sa.String(length=24), nullable=False),
        sa.Column("amount", sa.Integer(), nullable=False),
        sa.Column("paid_at", When, nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_prolific_replica_payments")),
    )
    op.create_index(
        op.f("ix_prolific_replica_payments_setup_id"), "prolific_replica_payments", ["setup_id"]
    )


def downgrade() -> None:
    for table, column in (
        ("prolific_replica_payments", "setup_id"),
        ("prolific_replica_bonus_setups", "study_id"),
        ("prolific_replica_submissions", "study_id"),
    ):
        op.drop_index(op.f(f"ix_{table}_{column}"), table_name=table)
        op.drop_table(table)
    op.drop_table("prolific_replica_studies")
    op.drop_table("prolific_events")
    with op.batch_alter_table("participants") as batch:
        batch.drop_column("prolific_status")
    # Unsettled intents have no place in the old schema (it records what the platform took).
    op.execute("DELETE FROM bonuses WHERE state <> 'paid'")
    op.execute("DELETE FROM assignment_reviews WHERE state <> 'done'")
    with op.batch_alter_table("bonuses") as batch:
        batch.alter_column("paid_at", existing_type=When, nullable=False)
        batch.alter_column("backend", type_=sa.String(length=16), existing_nullable=False)
        batch.drop_column("requested_at")
        batch.drop_column("setup_id")
        batch.drop_column("state")
        batch.drop_column("currency")
    with op.batch_alter_table("assignment_reviews") as batch:
        batch.alter_column("decided_at", existing_type=When, nullable=False)
        batch.alter_column("backend", type_=sa.String(length=16), existing_nullable=False)
        batch.drop_column("requested_at")
        batch.drop_column("state")
        batch.drop_column("rejection_category")
