"""Tables of the local Mechanical Turk replica (``routers/mturk.py``): the study's HIT, the
assignments workers accepted, returned or submitted (and the requester approved or rejected),
what each submission posted, and the bonuses the requester paid.

They live beside the study's tables (same declarative ``Base``, created by migration 0002) but
hold the platform's side only: the study's own data never refers to them.
"""

from __future__ import annotations

from datetime import datetime
from typing import Any

from sqlalchemy import JSON, Boolean, ForeignKey, Index, Integer, String, Text
from sqlalchemy.orm import Mapped, mapped_column

from server.app.storage.models import Base, UTCDateTime, utcnow


class ReplicaHit(Base):
    """The study listed as a HIT (one per database, made when the replica is first opened)."""

    __tablename__ = "mturk_replica_hits"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    hit_id: Mapped[str] = mapped_column(String(64), unique=True)
    title: Mapped[str] = mapped_column(String(200))
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)


class ReplicaAssignment(Base):
    """One worker's turn at an assignment. A returned assignment id is given to the next worker
    who accepts, as MTurk does, in a new row."""

    __tablename__ = "mturk_replica_assignments"
    __table_args__ = (Index("ix_mturk_replica_assignments_assignment_id", "assignment_id"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    hit_id: Mapped[str] = mapped_column(String(64))
    assignment_id: Mapped[str] = mapped_column(String(64))
    worker_id: Mapped[str] = mapped_column(String(128))
    # accepted, returned, submitted, then approved or rejected by the requester
    status: Mapped[str] = mapped_column(String(16))  # ReplicaAssignmentStatus
    accepted_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    returned_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    submitted_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    reviewed_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    requester_feedback: Mapped[str | None] = mapped_column(Text)


class ReplicaSubmission(Base):
    """What a page posted to ``/mturk/externalSubmit``: the assignment id and every field."""

    __tablename__ = "mturk_replica_submissions"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    assignment_row_id: Mapped[int] = mapped_column(
        ForeignKey("mturk_replica_assignments.id"), index=True
    )
    hit_id: Mapped[str] = mapped_column(String(64))
    assignment_id: Mapped[str] = mapped_column(String(64))
    worker_id: Mapped[str] = mapped_column(String(128))
    fields: Mapped[dict[str, Any]] = mapped_column(JSON)
    submitted_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)


class ReplicaBonus(Base):
    """A bonus the requester sent (``send_bonus``); a UniqueRequestToken is used once."""

    __tablename__ = "mturk_replica_bonuses"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    assignment_id: Mapped[str] = mapped_column(String(64), index=True)
    worker_id: Mapped[str] = mapped_column(String(128))
    amount: Mapped[str] = mapped_column(String(16))  # BonusAmount, US dollars as text
    reason: Mapped[str] = mapped_column(Text)
    unique_request_token: Mapped[str] = mapped_column(String(64), unique=True)
    granted_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)


# -- the local Prolific replica (``platforms/prolific_replica/``, ``routers/prolific.py``) --
class ProlificReplicaStudy(Base):
    """A study as Prolific keeps it: made as a draft (UNPUBLISHED) through ``POST /studies/``,
    with the fields it was made with."""

    __tablename__ = "prolific_replica_studies"

    id: Mapped[str] = mapped_column(String(24), primary_key=True)
    name: Mapped[str] = mapped_column(String(200))
    status: Mapped[str] = mapped_column(String(24))  # UNPUBLISHED, ACTIVE, PAUSED, ...
    external_study_url: Mapped[str] = mapped_column(Text)
    total_available_places: Mapped[int] = mapped_column(Integer)
    reward: Mapped[int] = mapped_column(Integer)  # cents of the currency
    maximum_allowed_time: Mapped[int] = mapped_column(Integer)  # minutes
    fields: Mapped[dict[str, Any]] = mapped_column(JSON)  # the study as it was made
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    published_at: Mapped[datetime | None] = mapped_column(UTCDateTime())


class ProlificReplicaSubmission(Base):
    """One participant's place in a study (the SESSION_ID), with Prolific's statuses."""

    __tablename__ = "prolific_replica_submissions"

    id: Mapped[str] = mapped_column(String(24), primary_key=True)
    study_id: Mapped[str] = mapped_column(String(24), index=True)
    participant_id: Mapped[str] = mapped_column(String(24))  # PROLIFIC_PID
    status: Mapped[str] = mapped_column(String(24))
    started_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    completed_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    study_code: Mapped[str | None] = mapped_column(String(64))  # the completion code given
    rejection_category: Mapped[str | None] = mapped_column(String(32))
    message: Mapped[str | None] = mapped_column(Text)  # a rejection's message
    reviewed_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    # When the participant was asked to return it (a completion code with REQUEST_RETURN).
    return_requested: Mapped[datetime | None] = mapped_column(UTCDateTime())


class ProlificReplicaBonusSetup(Base):
    """Bonuses set up (``POST /submissions/bonus-payments/``), not paid until ``pay``."""

    __tablename__ = "prolific_replica_bonus_setups"

    id: Mapped[str] = mapped_column(String(24), primary_key=True)
    study_id: Mapped[str] = mapped_column(String(24), index=True)
    csv_bonuses: Mapped[str] = mapped_column(Text)
    amount: Mapped[int] = mapped_column(Integer)  # cents, the bonuses' total
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)


class ProlificReplicaPayment(Base):
    """One participant paid by one ``pay`` of a set-up: a second ``pay`` of the same set-up pays
    again, as Prolific's does."""

    __tablename__ = "prolific_replica_payments"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    setup_id: Mapped[str] = mapped_column(String(24), index=True)
    participant_id: Mapped[str] = mapped_column(String(24))
    amount: Mapped[int] = mapped_column(Integer)  # cents
    paid_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)


class ProlificReplicaMessage(Base):
    """A message the researcher sent (``POST /messages/`` or ``/messages/bulk/``), one row per
    recipient, as Prolific lists them (``GET /messages/?user_id=``)."""

    __tablename__ = "prolific_replica_messages"

    id: Mapped[str] = mapped_column(String(24), primary_key=True)
    sender_id: Mapped[str] = mapped_column(String(24))
    recipient_id: Mapped[str] = mapped_column(String(24), index=True)  # PROLIFIC_PID
    study_id: Mapped[str] = mapped_column(String(24))
    body: Mapped[str] = mapped_column(Text)
    sent_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)


class ProlificReplicaHookSecret(Base):
    """The replica workspace's webhook signing secret (``POST /hooks/secrets/``: one per
    workspace, a new one replaces the old); made by the replica itself when it first sends
    a webhook without one, so that its events need no setting."""

    __tablename__ = "prolific_replica_hook_secrets"

    id: Mapped[str] = mapped_column(String(24), primary_key=True)
    workspace_id: Mapped[str] = mapped_column(String(24), unique=True)
    value: Mapped[str] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)


class ProlificReplicaSubscription(Base):
    """A webhook subscription (``POST /hooks/subscriptions/``): it delivers once confirmed
    with the ``X-Hook-Secret`` its creation answered."""

    __tablename__ = "prolific_replica_subscriptions"

    id: Mapped[str] = mapped_column(String(24), primary_key=True)
    workspace_id: Mapped[str] = mapped_column(String(24))
    event_type: Mapped[str] = mapped_column(String(64))
    target_url: Mapped[str] = mapped_column(Text)
    confirmation: Mapped[str] = mapped_column(String(64))  # the X-Hook-Secret
    is_enabled: Mapped[bool] = mapped_column(Boolean, default=False)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)


class ProlificReplicaHookEvent(Base):
    """One delivery of an event to a subscription's target (``GET
    /hooks/subscriptions/{id}/events/``): PENDING until the target answered, then SUCCEEDED
    (2xx) or FAILED."""

    __tablename__ = "prolific_replica_hook_events"

    id: Mapped[str] = mapped_column(String(24), primary_key=True)
    subscription_id: Mapped[str] = mapped_column(String(24), index=True)
    event_type: Mapped[str] = mapped_column(String(64))
    resource_id: Mapped[str] = mapped_column(String(24))
    status: Mapped[str] = mapped_column(String(16))
    target_url: Mapped[str] = mapped_column(Text)
    payload: Mapped[dict[str, Any]] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)


class ProlificReplicaParticipantGroup(Base):
    """A participant group (``POST /participant-groups/``) of the replica's workspace."""

    __tablename__ = "prolific_replica_participant_groups"

    id: Mapped[str] = mapped_column(String(24), primary_key=True)
    workspace_id: Mapped[str] = mapped_column(String(24))
    name: Mapped[str] = mapped_column(String(200))
    description: Mapped[str | None] = mapped_column(Text)
    is_deleted: Mapped[bool] = mapped_column(Boolean, default=False)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)


class ProlificReplicaGroupMember(Base):
    """A participant in a group: added by the API or by a completion code's
    ADD_TO_PARTICIPANT_GROUP action, taken out by REMOVE_FROM_PARTICIPANT_GROUP."""

    __tablename__ = "prolific_replica_group_members"

    group_id: Mapped[str] = mapped_column(String(24), primary_key=True)
    participant_id: Mapped[str] = mapped_column(String(24), primary_key=True)  # PROLIFIC_PID
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
