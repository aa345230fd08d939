"""A participant's further browsers keep their own tokens (``participant_tokens``): arriving
again without the first browser's cookie adds a token instead of replacing the first.

Revision ID: 0004
Revises: 0003
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0004"
down_revision: str | None = "0003"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "participant_tokens",
        sa.Column("token_hash", sa.String(length=64), nullable=False),
        sa.Column("participant_id", sa.Integer(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["participant_id"],
            ["participants.id"],
            name=op.f("fk_participant_tokens_participant_id_participants"),
        ),
        sa.PrimaryKeyConstraint("token_hash", name=op.f("pk_participant_tokens")),
    )
    op.create_index(
        op.f("ix_participant_tokens_participant_id"), "participant_tokens", ["participant_id"]
    )


def downgrade() -> None:
    op.drop_index(op.f("ix_participant_tokens_participant_id"), table_name="participant_tokens")
    op.drop_table("participant_tokens")
