"""Instructional attention checks between agents (``attention_checks``): one row per check of
a participant, with where the robot and the star are, the moves made and the outcome.

Revision ID: 0009
Revises: 0008
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0009"
down_revision: str | None = "0008"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "attention_checks",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("participant_id", sa.Integer(), nullable=False),
        sa.Column("number", sa.Integer(), nullable=False),
        sa.Column("after_ordinal", sa.Integer(), nullable=False),
        sa.Column("size", sa.Integer(), nullable=False),
        sa.Column("start_cell", sa.Integer(), nullable=False),
        sa.Column("star_cell", sa.Integer(), nullable=False),
        sa.Column("moves_allowed", sa.Integer(), nullable=False),
        sa.Column("status", sa.String(length=16), nullable=False),
        sa.Column("cell", sa.Integer(), nullable=False),
        sa.Column("moves", sa.JSON(), nullable=False),
        sa.Column("started_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("finished_at", sa.DateTime(timezone=True), nullable=True),
        sa.ForeignKeyConstraint(
            ["participant_id"],
            ["participants.id"],
            name=op.f("fk_attention_checks_participant_id_participants"),
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_attention_checks")),
        sa.UniqueConstraint(
            "participant_id", "number", name=op.f("uq_attention_checks_participant_id_number")
        ),
    )
    op.create_index(
        op.f("ix_attention_checks_participant_id"),
        "attention_checks",
        ["participant_id"],
        unique=False,
    )


def downgrade() -> None:
    op.drop_index(op.f("ix_attention_checks_participant_id"), table_name="attention_checks")
    op.drop_table("attention_checks")
