"""A study and a submission as the replica's API shows them, with the places a study holds
and the submissions under way."""

from __future__ import annotations

from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from server.app.platforms.prolific_replica.base import PROJECT_ID
from server.app.storage.replica_models import (
    ProlificReplicaBonusSetup,
    ProlificReplicaPayment,
    ProlificReplicaStudy,
    ProlificReplicaSubmission,
)

# A place is held by these; RETURNED, TIMED-OUT and REJECTED give it back.
HOLDING = ("RESERVED", "ACTIVE", "AWAITING REVIEW", "APPROVED")


def _submissions(s: Session, study_id: str, statuses: tuple[str, ...]) -> int:
    """The study's submissions in one of ``statuses``."""
    count = s.scalar(
        select(func.count())
        .select_from(ProlificReplicaSubmission)
        .where(
            ProlificReplicaSubmission.study_id == study_id,
            ProlificReplicaSubmission.status.in_(statuses),
        )
    )
    return int(count or 0)


def places_taken(s: Session, study_id: str) -> int:
    """The study's places held: a submission approved after it timed out (no completion code
    reached the study) holds none, as on Prolific, where approving it makes the participant an
    extra one."""
    extra = s.scalar(
        select(func.count())
        .select_from(ProlificReplicaSubmission)
        .where(
            ProlificReplicaSubmission.study_id == study_id,
            ProlificReplicaSubmission.status == "APPROVED",
            ProlificReplicaSubmission.study_code.is_(None),
        )
    )
    return _submissions(s, study_id, HOLDING) - int(extra or 0)


def taking_part(s: Session, study_id: str) -> int:
    """Submissions under way (what max_concurrent_submissions caps)."""
    return _submissions(s, study_id, ("RESERVED", "ACTIVE"))


def concurrency_limit(study: ProlificReplicaStudy) -> int | None:
    """The study's max_concurrent_submissions; None: no limit (-1 or not given)."""
    config = study.fields.get("submissions_config") or {}
    limit = config.get("max_concurrent_submissions", -1) if isinstance(config, dict) else -1
    return limit if isinstance(limit, int) and limit >= 1 else None


def study_view(s: Session, study: ProlificReplicaStudy) -> dict[str, Any]:
    return {
        **study.fields,
        "project": PROJECT_ID,  # the replica's one project (studies made before it had none)
        "id": study.id,
        "name": study.name,
        "status": study.status,
        "external_study_url": study.external_study_url,
        "total_available_places": study.total_available_places,
        "places_taken": places_taken(s, study.id),
        "reward": study.reward,
        "maximum_allowed_time": study.maximum_allowed_time,
        "date_created": study.created_at.isoformat(),
        "published_at": study.published_at.isoformat() if study.published_at else None,
    }


def submission_view(row: ProlificReplicaSubmission) -> dict[str, Any]:
    return {
        "id": row.id,
        "study_id": row.study_id,
        "participant_id": row.participant_id,
        "status": row.status,
        "started_at": row.started_at.isoformat(),
        "completed_at": row.completed_at.isoformat() if row.completed_at else None,
        "study_code": row.study_code,
        "return_requested": row.return_requested.isoformat() if row.return_requested else None,
    }


def submission_detail(s: Session, row: ProlificReplicaSubmission) -> dict[str, Any]:
    """``GET /submissions/{id}/``: the submission with its ``bonus_payments``, the bonuses paid
    on it in cents (each ``pay`` of a set-up that names its participant or it), as Prolific's
    SubmissionDetail lists them."""
    paid = s.scalars(
        select(ProlificReplicaPayment.amount)
        .join(
            ProlificReplicaBonusSetup,
            ProlificReplicaBonusSetup.id == ProlificReplicaPayment.setup_id,
        )
        .where(
            ProlificReplicaBonusSetup.study_id == row.study_id,
            ProlificReplicaPayment.participant_id == row.participant_id,
        )
        .order_by(ProlificReplicaPayment.id)
    ).all()
    return {**submission_view(row), "bonus_payments": list(paid)}
