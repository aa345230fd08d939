"""When the platform's status of a participant's submission was true:
``participants.platform_status_at``, so that a status Prolific reports out of order (its webhook's
``X-Timestamp``, older than the one stored) does not replace a newer one. Null for the rows before
it (any status then replaces theirs, as before).

Revision ID: 0011
Revises: 0010
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0011"
down_revision: str | None = "0010"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("participants") as batch:
        batch.add_column(sa.Column("platform_status_at", sa.DateTime(timezone=True), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("participants") as batch:
        batch.drop_column("platform_status_at")
