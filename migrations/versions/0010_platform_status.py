"""The participant's status on their platform, for any platform: ``participants.prolific_status``
is renamed ``platform_status`` (the values, Prolific's submission statuses, are kept).

The rename is SQLite's own ``ALTER TABLE ... RENAME COLUMN`` (SQLite 3.25 and later), not a batch
copy of the table: a copy would drop ``participants`` under the rows that refer to it.

Revision ID: 0010
Revises: 0009
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0010"
down_revision: str | None = "0009"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.alter_column(
        "participants",
        "prolific_status",
        new_column_name="platform_status",
        existing_type=sa.String(24),
    )


def downgrade() -> None:
    op.alter_column(
        "participants",
        "platform_status",
        new_column_name="prolific_status",
        existing_type=sa.String(24),
    )
