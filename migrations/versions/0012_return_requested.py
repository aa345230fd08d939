"""A return request kept where Prolific keeps it, and when a submission was completed:
``prolific_replica_submissions.return_requested`` (the replica's submission, as Prolific's
``return_requested``: a REQUEST_RETURN code such as NO_CONSENT completes the submission and asks
the participant to return it), and, on our side, ``participants.platform_return_requested_at``
and ``participants.platform_completed_at`` (when Prolific completed the submission: its
AWAITING REVIEW starts the 21 days after which Prolific approves it by itself). Null for the
rows before it.

Revision ID: 0012
Revises: 0011
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0012"
down_revision: str | None = "0011"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("prolific_replica_submissions") as batch:
        batch.add_column(sa.Column("return_requested", sa.DateTime(timezone=True), nullable=True))
    with op.batch_alter_table("participants") as batch:
        batch.add_column(
            sa.Column("platform_completed_at", sa.DateTime(timezone=True), nullable=True)
        )
        batch.add_column(
            sa.Column("platform_return_requested_at", sa.DateTime(timezone=True), nullable=True)
        )


def downgrade() -> None:
    with op.batch_alter_table("participants") as batch:
        batch.drop_column("platform_return_requested_at")
        batch.drop_column("platform_completed_at")
    with op.batch_alter_table("prolific_replica_submissions") as batch:
        batch.drop_column("return_requested")
