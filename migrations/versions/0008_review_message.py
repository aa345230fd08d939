"""One name for the text sent with a review: ``assignment_reviews.feedback`` becomes ``message``
(``feedback`` is the +/- signal everywhere else). The export keeps its published column name,
``reviews.csv``'s ``requester_feedback``.

Revision ID: 0008
Revises: 0007
"""

from __future__ import annotations

from collections.abc import Sequence

from alembic import op

revision: str = "0008"
down_revision: str | None = "0007"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("assignment_reviews") as batch:
        batch.alter_column("feedback", new_column_name="message")


def downgrade() -> None:
    with op.batch_alter_table("assignment_reviews") as batch:
        batch.alter_column("message", new_column_name="feedback")
