"""The experimenter's review of submitted work (``assignment_reviews``, ``bonuses``), the local
MTurk replica's side of it (approved or rejected assignments, ``mturk_replica_bonuses``), and
the answers to the post-study questionnaire (``questionnaire_answers``).

Revision ID: 0005
Revises: 0004
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0005"
down_revision: str | None = "0004"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

BigId = sa.BigInteger().with_variant(sa.Integer(), "sqlite")


def upgrade() -> None:
    op.create_table(
        "questionnaire_answers",
        sa.Column("id", BigId, nullable=False),
        sa.Column("participant_id", sa.Integer(), nullable=False),
        sa.Column("question_id", sa.String(length=64), nullable=False),
        sa.Column("kind", sa.String(length=16), nullable=False),
        sa.Column("question", sa.Text(), nullable=False),
        sa.Column("answer", sa.Text(), nullable=False),
        sa.Column("label", sa.Text(), nullable=True),
        sa.Column("answered_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["participant_id"],
            ["participants.id"],
            name=op.f("fk_questionnaire_answers_participant_id_participants"),
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_questionnaire_answers")),
        sa.UniqueConstraint(
            "participant_id",
            "question_id",
            name=op.f("uq_questionnaire_answers_participant_id_question_id"),
        ),
    )
    op.create_table(
        "assignment_reviews",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("participant_id", sa.Integer(), nullable=False),
        sa.Column("assignment_id", sa.String(length=128), nullable=False),
        sa.Column("worker_id", sa.String(length=128), nullable=False),
        sa.Column("decision", sa.String(length=16), nullable=False),
        sa.Column("feedback", sa.Text(), nullable=True),
        sa.Column("backend", sa.String(length=16), nullable=False),
        sa.Column("decided_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["participant_id"],
            ["participants.id"],
            name=op.f("fk_assignment_reviews_participant_id_participants"),
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_assignment_reviews")),
        sa.UniqueConstraint("assignment_id", name=op.f("uq_assignment_reviews_assignment_id")),
        sa.UniqueConstraint("participant_id", name=op.f("uq_assignment_reviews_participant_id")),
    )
    op.create_table(
        "bonuses",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("participant_id", sa.Integer(), nullable=False),
        sa.Column("assignment_id", sa.String(length=128), nullable=False),
        sa.Column("worker_id", sa.String(length=128), nullable=False),
        sa.Column("amount_cents", sa.Integer(), nullable=False),
        sa.Column("reason", sa.Text(), nullable=False),
        sa.Column("unique_token", sa.String(length=64), nullable=False),
        sa.Column("backend", sa.String(length=16), nullable=False),
        sa.Column("paid_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["participant_id"],
            ["participants.id"],
            name=op.f("fk_bonuses_participant_id_participants"),
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_bonuses")),
        sa.UniqueConstraint("unique_token", name=op.f("uq_bonuses_unique_token")),
    )
    op.create_index(op.f("ix_bonuses_participant_id"), "bonuses", ["participant_id"])
    op.add_column(
        "mturk_replica_assignments",
        sa.Column("reviewed_at", sa.DateTime(timezone=True), nullable=True),
    )
    op.add_column(
        "mturk_replica_assignments", sa.Column("requester_feedback", sa.Text(), nullable=True)
    )
    op.create_table(
        "mturk_replica_bonuses",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("assignment_id", sa.String(length=64), nullable=False),
        sa.Column("worker_id", sa.String(length=128), nullable=False),
        sa.Column("amount", sa.String(length=16), nullable=False),
        sa.Column("reason", sa.Text(), nullable=False),
        sa.Column("unique_request_token", sa.String(length=64), nullable=False),
        sa.Column("granted_at", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_mturk_replica_bonuses")),
        sa.UniqueConstraint(
            "unique_request_token", name=op.f("uq_mturk_replica_bonuses_unique_request_token")
        ),
    )
    op.create_index(
        op.f("ix_mturk_replica_bonuses_assignment_id"), "mturk_replica_bonuses", ["assignment_id"]
    )


def downgrade() -> None:
    op.drop_index(
        op.f("ix_mturk_replica_bonuses_assignment_id"), table_name="mturk_replica_bonuses"
    )
    op.drop_table("mturk_replica_bonuses")
    with op.batch_alter_table("mturk_replica_assignments") as batch:
        batch.drop_column("requester_feedback")
        batch.drop_column("reviewed_at")
    op.drop_index(op.f("ix_bonuses_participant_id"), table_name="bonuses")
    op.drop_table("bonuses")
    op.drop_table("assignment_reviews")
    op.drop_table("questionnaire_answers")
