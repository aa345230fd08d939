"""When Prolific's ``pay`` of a bonus was sent: ``bonuses.pay_sent_at``, so that a bonus whose
``pay`` failed after it may have paid (a 429, a time-out, an error) is held in doubt and settled
from Prolific's record of the submission's bonuses, not paid again: Prolific pays "in the
following minutes", so a bonus it does not list is taken as unpaid only once that time has
passed since the pay was sent. A bonus left ``paying`` before this revision gets the time of the
upgrade (its pay was sent before then).

Revision ID: 0013
Revises: 0012
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0013"
down_revision: str | None = "0012"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("bonuses") as batch:
        batch.add_column(sa.Column("pay_sent_at", sa.DateTime(timezone=True), nullable=True))
    op.execute("UPDATE bonuses SET pay_sent_at = CURRENT_TIMESTAMP WHERE state = 'paying'")


def downgrade() -> None:
    with op.batch_alter_table("bonuses") as batch:
        batch.drop_column("pay_sent_at")
