"""Several study servers on one database: claims on pending learner updates (the claiming
server, its lease, the runs taken, the server a lease was taken from), the awaited agent of a
learning session, and the deployment's shared tables: its servers with their heartbeats, the
dashboard's sessions, the failed sign-ins, and the latest run of each periodic job.

Revision ID: 0017
Revises: 0016
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0017"
down_revision: str | None = "0016"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

When = sa.DateTime(timezone=True)
BigId = sa.BigInteger().with_variant(sa.Integer(), "sqlite")


def upgrade() -> None:
    with op.batch_alter_table("learner_updates") as batch:
        batch.add_column(sa.Column("claimed_by", sa.String(length=64), nullable=True))
        batch.add_column(sa.Column("lease_until", When, nullable=True))
        batch.add_column(sa.Column("runs", sa.Integer(), server_default="0", nullable=False))
        batch.add_column(sa.Column("taken_from", sa.String(length=64), nullable=True))
    with op.batch_alter_table("learning_sessions") as batch:
        batch.add_column(sa.Column("awaited_since", When, nullable=True))
        batch.add_column(sa.Column("awaited_update", sa.Integer(), nullable=True))
    # Updates done before this revision ran once each.
    op.execute("UPDATE learner_updates SET runs = 1 WHERE status <> 'pending'")
    op.create_table(
        "servers",
        sa.Column("name", sa.String(length=64), nullable=False),
        sa.Column("host", sa.String(length=255), nullable=False),
        sa.Column("pid", sa.Integer(), nullable=False),
        sa.Column("started_at", When, nullable=False),
        sa.Column("heartbeat_at", When, nullable=False),
        sa.Column("stopped_at", When, nullable=True),
        sa.Column("update_slots", sa.Integer(), nullable=False),
        sa.Column("updates_running", sa.Integer(), nullable=False),
        sa.Column("updates_completed", sa.Integer(), nullable=False),
        sa.Column("updates_failed", sa.Integer(), nullable=False),
        sa.Column("participants_at_once", sa.Integer(), nullable=True),
        sa.PrimaryKeyConstraint("name", name=op.f("pk_servers")),
    )
    op.create_table(
        "admin_sessions",
        sa.Column("id_hash", sa.String(length=64), nullable=False),
        sa.Column("expires", sa.BigInteger(), nullable=False),
        sa.PrimaryKeyConstraint("id_hash", name=op.f("pk_admin_sessions")),
    )
    op.create_index(op.f("ix_admin_sessions_expires"), "admin_sessions", ["expires"])
    op.create_table(
        "sign_in_failures",
        sa.Column("id", BigId, autoincrement=True, nullable=False),
        sa.Column("address", sa.String(length=64), nullable=False),
        sa.Column("failed_at", sa.Float(), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_sign_in_failures")),
    )
    op.create_index("ix_sign_in_failures_address", "sign_in_failures", ["address", "failed_at"])
    op.create_index(op.f("ix_sign_in_failures_failed_at"), "sign_in_failures", ["failed_at"])
    op.create_table(
        "periodic_runs",
        sa.Column("job", sa.String(length=64), nullable=False),
        sa.Column("ran_at", When, nullable=False),
        sa.Column("ran_by", sa.String(length=64), nullable=False),
        sa.PrimaryKeyConstraint("job", name=op.f("pk_periodic_runs")),
    )


def downgrade() -> None:
    op.drop_table("periodic_runs")
    op.drop_index(op.f("ix_sign_in_failures_failed_at"), table_name="sign_in_failures")
    op.drop_index("ix_sign_in_failures_address", table_name="sign_in_failures")
    op.drop_table("sign_in_failures")
    op.drop_index(op.f("ix_admin_sessions_expires"), table_name="admin_sessions")
    op.drop_table("admin_sessions")
    op.drop_table("servers")
    with op.batch_alter_table("learning_sessions") as batch:
        batch.drop_column("awaited_update")
        batch.drop_column("awaited_since")
    with op.batch_alter_table("learner_updates") as batch:
        batch.drop_column("taken_from")
        batch.drop_column("runs")
        batch.drop_column("lease_until")
        batch.drop_column("claimed_by")
