"""Submissions: listed page by page and counted per status, approved or rejected (one at a
time or in bulk), and what a completion code asks of them (a return)."""

from __future__ import annotations

from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from server.app.platforms.prolific import SUBMISSION_STATUSES
from server.app.platforms.prolific_replica.base import Refusal, _study, _submission
from server.app.platforms.prolific_replica.views import submission_view
from server.app.platforms.review import REJECTION_CATEGORIES
from server.app.storage.models import utcnow
from server.app.storage.replica_models import (
    ProlificReplicaSubmission,
)

SUBMISSION_ACTIONS = {"APPROVE": "APPROVED", "REJECT": "REJECTED"}
# The statuses each decision is taken from. A TIMED-OUT submission can be approved as well:
# "You will not be charged for this submission, but you can also manually approve them if you
# wish" (researcher-help.prolific.com, "Timed out submission status"), which pays a timed-out
# participant who finished.
DECIDED_FROM = {"APPROVE": ("AWAITING REVIEW", "TIMED-OUT"), "REJECT": ("AWAITING REVIEW",)}
MIN_REJECTION_MESSAGE = 100


def list_submissions(s: Session, query: dict[str, str]) -> tuple[int, Any]:
    study_id = query.get("study")
    if not study_id:
        raise Refusal(400, "study: a study id is required to list submissions.")
    _study(s, study_id)
    try:
        page = int(query.get("page", "1"))
        size = int(query.get("page_size", "20"))
    except ValueError:
        raise Refusal(400, "page and page_size are whole numbers.") from None
    if page < 1 or not 1 <= size <= 200:
        raise Refusal(400, "page from 1, page_size from 1 to 200.")
    where = [ProlificReplicaSubmission.study_id == study_id]
    if query.get("status"):
        # The filter spells statuses with underscores (AWAITING_REVIEW), as Prolific's does.
        spelt = {name.replace(" ", "_").replace("-", "_"): name for name in SUBMISSION_STATUSES}
        status = spelt.get(query["status"], query["status"])
        where.append(ProlificReplicaSubmission.status == status)
    newest_first = query.get("ordering") == "-started_at"  # else by started_at
    total = int(
        s.scalar(select(func.count()).select_from(ProlificReplicaSubmission).where(*where)) or 0
    )
    rows = s.scalars(
        select(ProlificReplicaSubmission)
        .where(*where)
        .order_by(
            *(
                (ProlificReplicaSubmission.started_at.desc(), ProlificReplicaSubmission.id.desc())
                if newest_first
                else (ProlificReplicaSubmission.started_at, ProlificReplicaSubmission.id)
            )
        )
        .offset((page - 1) * size)
        .limit(size)
    ).all()
    following = None
    if page * size < total:
        kept = "".join(f"&{k}={query[k]}" for k in ("status", "ordering") if query.get(k))
        following = {
            "href": f"submissions/?study={study_id}&page={page + 1}&page_size={size}{kept}"
        }
    return 200, {
        "results": [submission_view(r) for r in rows],
        "_links": {"next": following},
        "meta": {"count": total},
    }


# The statuses ``GET /studies/{id}/submissions/counts/`` counts (its SubmissionsCountResponse).
COUNTED_STATUSES = (
    "ACTIVE",
    "APPROVED",
    "AWAITING REVIEW",
    "REJECTED",
    "RESERVED",
    "RETURNED",
    "TIMED-OUT",
    "PARTIALLY APPROVED",
    "SCREENED OUT",
)


def submission_counts(s: Session, study_id: str) -> tuple[int, Any]:
    """``GET /studies/{id}/submissions/counts/``: the study's submissions per status (each of
    Prolific's, 0 where none) and their ``TOTAL``."""
    _study(s, study_id)
    counted = dict(
        s.execute(
            select(ProlificReplicaSubmission.status, func.count())
            .where(ProlificReplicaSubmission.study_id == study_id)
            .group_by(ProlificReplicaSubmission.status)
        ).all()
    )
    counts = {status: int(counted.get(status, 0)) for status in COUNTED_STATUSES}
    return 200, {**counts, "TOTAL": int(sum(counted.values()))}


def transition_submission(s: Session, submission_id: str, body: dict[str, Any]) -> tuple[int, Any]:
    row = _submission(s, submission_id)
    action = body.get("action")
    if action not in SUBMISSION_ACTIONS:
        raise Refusal(400, f"action: one of {', '.join(SUBMISSION_ACTIONS)}.")
    target = SUBMISSION_ACTIONS[action]
    if action == "REJECT":
        message = body.get("message")
        if not isinstance(message, str) or len(message) < MIN_REJECTION_MESSAGE:
            raise Refusal(400, "message: a rejection message is at least 100 characters long.")
        if body.get("rejection_category") not in REJECTION_CATEGORIES:
            raise Refusal(400, f"rejection_category: one of {', '.join(REJECTION_CATEGORIES)}.")
    if row.status == target:  # idempotent: the same request again is ignored
        return 200, submission_view(row)
    if row.status not in DECIDED_FROM[action]:
        raise Refusal(400, f"A submission that is {row.status} cannot be {target.lower()}.")
    row.status = target
    row.reviewed_at = utcnow()
    if action == "REJECT":
        row.message = body["message"]
        row.rejection_category = body["rejection_category"]
    return 200, submission_view(row)


def requests_return(code: dict[str, Any]) -> bool:
    """Whether a completion code (one of the study's ``completion_codes``) asks the participant
    to return the submission (its actions include REQUEST_RETURN, as our NO_CONSENT code's)."""
    actions = code.get("actions") or []
    return any(isinstance(a, dict) and a.get("action") == "REQUEST_RETURN" for a in actions)


def return_reason(code: dict[str, Any]) -> str:
    """The return reason of the code's REQUEST_RETURN action ('' without one)."""
    actions = code.get("actions") or []
    for action in actions:
        if isinstance(action, dict) and action.get("action") == "REQUEST_RETURN":
            return str(action.get("return_reason") or "")
    return ""


def bulk_approve(s: Session, body: dict[str, Any]) -> tuple[int, Any]:
    ids = body.get("submission_ids")
    if not isinstance(ids, list) or not ids or not all(isinstance(i, str) for i in ids):
        raise Refusal(400, "submission_ids: a list of submission ids is required.")
    rows = [_submission(s, i) for i in ids]
    for row in rows:
        if row.status not in ("AWAITING REVIEW", "APPROVED"):
            raise Refusal(400, f"Submission {row.id} is {row.status}: it cannot be approved.")
    for row in rows:
        if row.status != "APPROVED":
            row.status = "APPROVED"
            row.reviewed_at = utcnow()
    return 200, "The request to bulk approve has been made successfully."
