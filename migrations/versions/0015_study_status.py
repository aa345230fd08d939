"""What Prolific's study events said of a study: ``prolific_studies`` holds its Prolific status
and when it took it (``study.status.change``), and the last ``study.has_high_return_rate``
warning with its metadata.

Revision ID: 0015
Revises: 0014
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0015"
down_revision: str | None = "0014"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

When = sa.DateTime(timezone=True)


def upgrade() -> None:
    op.create_table(
        "prolific_studies",
        sa.Column("study_id", sa.String(length=64), nullable=False),
        sa.Column("status", sa.String(length=24), nullable=True),
        sa.Column("status_at", When, nullable=True),
        sa.Column("high_return_rate_at", When, nullable=True),
        sa.Column("high_return_rate_metadata", sa.JSON(), nullable=True),
        sa.PrimaryKeyConstraint("study_id", name=op.f("pk_prolific_studies")),
    )


def downgrade() -> None:
    op.drop_table("prolific_studies")
