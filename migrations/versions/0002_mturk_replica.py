"""The local Mechanical Turk replica's tables: its HIT, the assignments and the submissions
posted to ``/mturk/externalSubmit`` (``server/app/replica_models.py``).

Revision ID: 0002
Revises: 0001
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0002"
down_revision: str | None = "0001"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "mturk_replica_hits",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("hit_id", sa.String(length=64), nullable=False),
        sa.Column("title", sa.String(length=200), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_mturk_replica_hits")),
        sa.UniqueConstraint("hit_id", name=op.f("uq_mturk_replica_hits_hit_id")),
    )
    op.create_table(
        "mturk_replica_assignments",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("hit_id", sa.String(length=64), nullable=False),
        sa.Column("assignment_id", sa.String(length=64), nullable=False),
        sa.Column("worker_id", sa.String(length=128), nullable=False),
        sa.Column("status", sa.String(length=16), nullable=False),
        sa.Column("accepted_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("returned_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("submitted_at", sa.DateTime(timezone=True), nullable=True),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_mturk_replica_assignments")),
    )
    op.create_index(
        "ix_mturk_replica_assignments_assignment_id",
        "mturk_replica_assignments",
        ["assignment_id"],
    )
    op.create_table(
        "mturk_replica_submissions",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("assignment_row_id", sa.Integer(), nullable=False),
        sa.Column("hit_id", sa.String(length=64), nullable=False),
        sa.Column("assignment_id", sa.String(length=64), nullable=False),
        sa.Column("worker_id", sa.String(length=128), nullable=False),
        sa.Column("fields", sa.JSON(), nullable=False),
        sa.Column("submitted_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["assignment_row_id"],
            ["mturk_replica_assignments.id"],
            name=op.f("fk_mturk_replica_submissions_assignment_row_id_mturk_replica_assignments"),
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_mturk_replica_submissions")),
    )
    op.create_index(
        op.f("ix_mturk_replica_submissions_assignment_row_id"),
        "mturk_replica_submissions",
        ["assignment_row_id"],
    )


def downgrade() -> None:
    op.drop_index(
        op.f("ix_mturk_replica_submissions_assignment_row_id"),
        table_name="mturk_replica_submissions",
    )
    op.drop_table("mturk_replica_submissions")
    op.drop_index(
        "ix_mturk_replica_assignments_assignment_id", table_name="mturk_replica_assignments"
    )
    op.drop_table("mturk_replica_assignments")
    op.drop_table("mturk_replica_hits")
