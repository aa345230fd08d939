"""Where the participant is on the page, kept on the server: the tutorial step reached
(``participants.tutorial_step``) and when the participant began teaching a learning session
after its introduction page (``learning_sessions.opened_at``). Sessions started before this
revision count as opened when they started.

Revision ID: 0003
Revises: 0002
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0003"
down_revision: str | None = "0002"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("participants") as batch:
        batch.add_column(
            sa.Column("tutorial_step", sa.Integer(), nullable=False, server_default="0")
        )
    with op.batch_alter_table("learning_sessions") as batch:
        batch.add_column(sa.Column("opened_at", sa.DateTime(timezone=True), nullable=True))
    op.execute("UPDATE learning_sessions SET opened_at = started_at WHERE started_at IS NOT NULL")


def downgrade() -> None:
    with op.batch_alter_table("learning_sessions") as batch:
        batch.drop_column("opened_at")
    with op.batch_alter_table("participants") as batch:
        batch.drop_column("tutorial_step")
