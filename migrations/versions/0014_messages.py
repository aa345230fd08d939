"""Messages to participants through Prolific's messages API (``bam-study prolific message``):
``messages``, one row per recipient of each message Prolific took (erased with the participant,
their PROLIFIC_PID scrubbed like their other ids), and ``prolific_replica_messages``, the
replica's record of the messages sent to it (as Prolific's ``GET /messages/`` lists them).

Revision ID: 0014
Revises: 0013
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0014"
down_revision: str | None = "0013"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

When = sa.DateTime(timezone=True)


def upgrade() -> None:
    op.create_table(
        "messages",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("participant_id", sa.Integer(), nullable=False),
        sa.Column("worker_id", sa.String(length=128), nullable=False),
        sa.Column("study_id", sa.String(length=128), nullable=False),
        sa.Column("body", sa.Text(), nullable=False),
        sa.Column("backend", sa.String(length=24), nullable=False),
        sa.Column("sent_with", sa.String(length=32), nullable=False),
        sa.Column("answer_status", sa.Integer(), nullable=False),
        sa.Column("sent_at", When, nullable=False),
        sa.ForeignKeyConstraint(
            ["participant_id"],
            ["participants.id"],
            name=op.f("fk_messages_participant_id_participants"),
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_messages")),
    )
    op.create_index(op.f("ix_messages_participant_id"), "messages", ["participant_id"])
    op.create_table(
        "prolific_replica_messages",
        sa.Column("id", sa.String(length=24), nullable=False),
        sa.Column("sender_id", sa.String(length=24), nullable=False),
        sa.Column("recipient_id", sa.String(length=24), nullable=False),
        sa.Column("study_id", sa.String(length=24), nullable=False),
        sa.Column("body", sa.Text(), nullable=False),
        sa.Column("sent_at", When, nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_prolific_replica_messages")),
    )
    op.create_index(
        op.f("ix_prolific_replica_messages_recipient_id"),
        "prolific_replica_messages",
        ["recipient_id"],
    )


def downgrade() -> None:
    op.drop_index(
        op.f("ix_prolific_replica_messages_recipient_id"), table_name="prolific_replica_messages"
    )
    op.drop_table("prolific_replica_messages")
    op.drop_index(op.f("ix_messages_participant_id"), table_name="messages")
    op.drop_table("messages")
