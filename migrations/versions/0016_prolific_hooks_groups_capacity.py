"""Prolific's webhooks, participant groups and the study's capacity: ``prolific_webhook_secrets``
(the workspace's signing secret that ``bam-study prolific hooks`` made, read by the webhook),
``prolific_study_changes`` (each change the server made to its study by itself: the
concurrency, a pause, a start), and the replica's hook secret, subscriptions, deliveries,
participant groups and their members.

Revision ID: 0016
Revises: 0015
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0016"
down_revision: str | None = "0015"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

When = sa.DateTime(timezone=True)


def upgrade() -> None:
    op.create_table(
        "prolific_webhook_secrets",
        sa.Column("workspace_id", sa.String(length=64), nullable=False),
        sa.Column("secret", sa.Text(), nullable=False),
        sa.Column("created_at", When, nullable=False),
        sa.PrimaryKeyConstraint("workspace_id", name=op.f("pk_prolific_webhook_secrets")),
    )
    op.create_table(
        "prolific_study_changes",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("study_id", sa.String(length=64), nullable=False),
        sa.Column("at", When, nullable=False),
        sa.Column("change", sa.String(length=32), nullable=False),
        sa.Column("value", sa.Integer(), nullable=True),
        sa.Column("reason", sa.Text(), nullable=False),
        sa.Column("outcome", sa.Text(), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_prolific_study_changes")),
    )
    op.create_index(
        op.f("ix_prolific_study_changes_study_id"), "prolific_study_changes", ["study_id"]
    )
    op.create_table(
        "prolific_replica_hook_secrets",
        sa.Column("id", sa.String(length=24), nullable=False),
        sa.Column("workspace_id", sa.String(length=24), nullable=False),
        sa.Column("value", sa.Text(), nullable=False),
        sa.Column("created_at", When, nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_prolific_replica_hook_secrets")),
        sa.UniqueConstraint(
            "workspace_id", name=op.f("uq_prolific_replica_hook_secrets_workspace_id")
        ),
    )
    op.create_table(
        "prolific_replica_subscriptions",
        sa.Column("id", sa.String(length=24), nullable=False),
        sa.Column("workspace_id", sa.String(length=24), nullable=False),
        sa.Column("event_type", sa.String(length=64), nullable=False),
        sa.Column("target_url", sa.Text(), nullable=False),
        sa.Column("confirmation", sa.String(length=64), nullable=False),
        sa.Column("is_enabled", sa.Boolean(), nullable=False),
        sa.Column("created_at", When, nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_prolific_replica_subscriptions")),
    )
    op.create_table(
        "prolific_replica_hook_events",
        sa.Column("id", sa.String(length=24), nullable=False),
        sa.Column("subscription_id", sa.String(length=24), nullable=False),
        sa.Column("event_type", sa.String(length=64), nullable=False),
        sa.Column("resource_id", sa.String(length=24), nullable=False),
        sa.Column("status", sa.String(length=16), nullable=False),
        sa.Column("target_url", sa.Text(), nullable=False),
        sa.Column("payload", sa.JSON(), nullable=False),
        sa.Column("created_at", When, nullable=False),
        sa.Column("updated_at", When, nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_prolific_replica_hook_events")),
    )
    op.create_index(
        op.f("ix_prolific_replica_hook_events_subscription_id"),
        "prolific_replica_hook_events",
        ["subscription_id"],
    )
    op.create_table(
        "prolific_replica_participant_groups",
        sa.Column("id", sa.String(length=24), nullable=False),
        sa.Column("workspace_id", sa.String(length=24), nullable=False),
        sa.Column("name", sa.String(length=200), nullable=False),
        sa.Column("description", sa.Text(), nullable=True),
        sa.Column("is_deleted", sa.Boolean(), nullable=False),
        sa.Column("created_at", When, nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_prolific_replica_participant_groups")),
    )
    op.create_table(
        "prolific_replica_group_members",
        sa.Column("group_id", sa.String(length=24), nullable=False),
        sa.Column("participant_id", sa.String(length=24), nullable=False),
        sa.Column("created_at", When, nullable=False),
        sa.PrimaryKeyConstraint(
            "group_id", "participant_id", name=op.f("pk_prolific_replica_group_members")
        ),
    )


def downgrade() -> None:
    op.drop_table("prolific_replica_group_members")
    op.drop_table("prolific_replica_participant_groups")
    op.drop_index(
        op.f("ix_prolific_replica_hook_events_subscription_id"),
        table_name="prolific_replica_hook_events",
    )
    op.drop_table("prolific_replica_hook_events")
    op.drop_table("prolific_replica_subscriptions")
    op.drop_table("prolific_replica_hook_secrets")
    op.drop_index(op.f("ix_prolific_study_changes_study_id"), table_name="prolific_study_changes")
    op.drop_table("prolific_study_changes")
    op.drop_table("prolific_webhook_secrets")
