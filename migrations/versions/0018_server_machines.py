"""The machine each server's update slots run on, and the costs its capacity was stated from,
in its heartbeat: the deployment's capacity counts each machine's cores once, however many
servers share it.

Revision ID: 0018
Revises: 0017
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0018"
down_revision: str | None = "0017"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("servers") as batch:
        # Servers that ran before this revision: where their slots ran is not known.
        batch.add_column(
            sa.Column("machine", sa.String(length=255), server_default="", nullable=False)
        )
        batch.add_column(sa.Column("cores", sa.Integer(), nullable=True))
        batch.add_column(sa.Column("update_seconds", sa.Float(), nullable=True))
        batch.add_column(sa.Column("server_seconds", sa.Float(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("servers") as batch:
        batch.drop_column("server_seconds")
        batch.drop_column("update_seconds")
        batch.drop_column("cores")
        batch.drop_column("machine")
