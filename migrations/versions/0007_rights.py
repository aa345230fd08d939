"""Participants' rights: the audit trail of erasures (``erasures``), and when a participant's
platform ids were replaced by their pseudonyms (``participants.identifiers_scrubbed_at``).

Revision ID: 0007
Revises: 0006p
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0007"
down_revision: str | None = "0006p"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "erasures",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("erased_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("erased_by", sa.String(length=16), nullable=False),
        sa.Column("participant_id", sa.Integer(), nullable=False),
        sa.Column("platform", sa.String(length=16), nullable=False),
        sa.Column("worker_pseudonym", sa.String(length=32), nullable=True),
        sa.Column("assignment_pseudonym", sa.String(length=32), nullable=True),
        sa.Column("rows", sa.JSON(), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_erasures")),
    )
    with op.batch_alter_table("participants") as batch:
        batch.add_column(
            sa.Column("identifiers_scrubbed_at", sa.DateTime(timezone=True), nullable=True)
        )


def downgrade() -> None:
    with op.batch_alter_table("participants") as batch:
        batch.drop_column("identifiers_scrubbed_at")
    op.drop_table("erasures")
