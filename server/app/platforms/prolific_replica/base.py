"""What the replica's parts share: where it is served, its one workspace and project, the
study changes it reports, its ids, and its refusals (``Refusal``, answered as Prolific's error
body)."""

from __future__ import annotations

import secrets
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from server.app.storage.replica_models import (
    ProlificReplicaStudy,
    ProlificReplicaSubmission,
)

# Where this server serves the replica (its pages, its API under /api/v1, and the completion
# URL that stands in for app.prolific.com's: /submissions/complete?cc=CODE).
REPLICA_PATH = "/prolific"
PLACEHOLDERS = ("{{%PROLIFIC_PID%}}", "{{%STUDY_ID%}}", "{{%SESSION_ID%}}")
# The replica's one workspace and project: every study is made in them.
WORKSPACE_ID = "5e0f000000000000000000a1"
PROJECT_ID = "5e0f000000000000000000b1"


@dataclass(frozen=True)
class StudyChange:
    """A replica study took a new status (Prolific sends ``study.status.change``)."""

    study_id: str
    status: str
    at: datetime


@dataclass(frozen=True)
class Workspace:
    """The replica's workspace: its currency and the funds put in it, in cents."""

    currency: str = "GBP"
    funds: int = 100_000


def workspace_of(settings: Any) -> Workspace:
    """The replica's workspace for the server's settings: BAM_PROLIFIC_CURRENCY, and
    BAM_PROLIFIC_REPLICA_FUNDS put in it."""
    return Workspace(settings.prolific_currency, int(settings.prolific_replica_funds * 100))


class Refusal(Exception):
    def __init__(self, status: int, detail: str) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail


def is_replica_study(s: Session | Any, study_id: str) -> bool:
    """Whether ``study_id`` is a study of this server's replica (``s``: a session or a
    connection)."""
    found = s.execute(select(ProlificReplicaStudy.id).where(ProlificReplicaStudy.id == study_id))
    return found.first() is not None


def completion_url(code: str) -> str:
    """The replica's completion URL, which stands in for Prolific's."""
    return f"{REPLICA_PATH}/submissions/complete?cc={code}"


def new_id() -> str:
    """An id shaped like Prolific's (24 hexadecimal digits)."""
    return secrets.token_hex(12)


def error_body(status: int, detail: str) -> dict[str, Any]:
    titles = {
        400: "Bad request",
        401: "Unauthorized",
        404: "Not found",
        405: "Not allowed",
        429: "Too many requests",
    }
    return {"error": {"status": status, "title": titles.get(status, "Error"), "detail": detail}}


def _study(s: Session, study_id: str) -> ProlificReplicaStudy:
    study = s.get(ProlificReplicaStudy, study_id)
    if study is None:
        raise Refusal(404, f"Study {study_id} not found.")
    return study


def _submission(s: Session, submission_id: str) -> ProlificReplicaSubmission:
    row = s.get(ProlificReplicaSubmission, submission_id)
    if row is None:
        raise Refusal(404, f"Submission {submission_id} not found.")
    return row


def _positive_int(body: dict[str, Any], name: str) -> int:
    value = body.get(name)
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise Refusal(400, f"{name}: a positive whole number is required.")
    return value


def _workspace_id(value: Any) -> str:
    if value != WORKSPACE_ID:
        raise Refusal(400, f"workspace_id: {value!r} is not a workspace of yours.")
    return WORKSPACE_ID
