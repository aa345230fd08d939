"""The platforms' own views: the MTurk replica's records, and a Prolific study as its events
and our participants show it."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import (
    BaseModel,
    Field,
)


class ReplicaAssignmentView(BaseModel):
    row: int
    hit_id: str
    assignment_id: str
    worker_id: str
    status: str
    accepted_at: datetime
    returned_at: datetime | None
    submitted_at: datetime | None


class ReplicaSubmissionView(BaseModel):
    assignment_id: str
    worker_id: str
    hit_id: str
    fields: dict[str, Any]
    submitted_at: datetime


class ReplicaRecords(BaseModel):
    """The MTurk replica's assignments and every submission it recorded."""

    assignments: list[ReplicaAssignmentView]
    submissions: list[ReplicaSubmissionView]


class HighReturnRateView(BaseModel):
    """Prolific's ``study.has_high_return_rate`` warning beside our own count of the returns."""

    warned_at: datetime = Field(description="When Prolific raised the warning (its last one).")
    metadata: dict[str, Any] = Field(description="The event's metadata, as Prolific sent it.")
    arrived: int = Field(description="Our participants of the study (each took a place).")
    returned: int = Field(
        description="Of them, those whose submission was RETURNED or TIMED-OUT, or whom the "
        "study released."
    )
    share_returned: float | None = Field(description="returned / arrived (none: no one arrived).")
    reasons: dict[str, int] = Field(
        description="Why they returned, as far as our records say: 'returned on Prolific', "
        "'timed out', and, among those, 'had declined consent'."
    )


class ProlificStudyChangeView(BaseModel):
    """A change the server made to the study on Prolific by itself (its capacity)."""

    at: datetime
    change: str = Field(description="max_concurrent_submissions, PAUSE or START.")
    value: int | None = Field(description="The new max_concurrent_submissions.")
    reason: str
    outcome: str = Field(description="done, or Prolific's refusal.")


class ProlificStudyView(BaseModel):
    """A Prolific study as its events (``study.status.change``) and our participants show it."""

    study_id: str
    status: str | None = Field(description="Prolific's status of the study (none: no event yet).")
    status_at: datetime | None = Field(description="When the study took that status.")
    high_return_rate: HighReturnRateView | None
    changes: list[ProlificStudyChangeView] = Field(
        default_factory=list,
        description="The server's own last changes to the study (its concurrency, pauses and "
        "starts held to the capacity), newest first.",
    )
