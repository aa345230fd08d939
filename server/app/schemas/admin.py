"""The admin API's bodies: exclusions, reviews and bonuses (one participant's or several at
once), the participants and sessions as the dashboard lists them, a session's replay, the
update queue and the deployment's servers."""

from __future__ import annotations

from datetime import datetime
from decimal import Decimal
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    BeforeValidator,
    Field,
    field_validator,
)

from server.app.platforms.review import MAX_BONUS, RejectionCategory, message_text, parse_amount
from server.app.schemas.base import Body, ReviewDecision, ReviewState


class ExclusionRequest(Body):
    reason: str = Field(min_length=1, max_length=2000)


class ReviewRequest(Body):
    """Approve or reject the participant's submitted work (an MTurk assignment or a Prolific
    submission)."""

    message: str | None = Field(
        None,
        max_length=1024,
        description="Shown to the participant (needed for a rejection: MTurk's "
        "RequesterFeedback; on Prolific the rejection message, at least 100 characters).",
    )
    rejection_category: RejectionCategory | None = Field(
        None, description="Prolific's rejection category (needed to reject on Prolific)."
    )

    @field_validator("message", mode="after")
    @classmethod
    def _shown_text(cls, value: str | None) -> str | None:
        return None if value is None else message_text(value, "message")


class BulkApprovalRequest(Body):
    """Approve several participants' submitted work at once (each once, as one approval)."""

    participant_ids: list[Annotated[int, Field(ge=1, le=2**31 - 1)]] = Field(
        min_length=1,
        max_length=1000,
        description="The participants to approve (at most 1,000, as Prolific recommends).",
    )
    message: str | None = Field(None, max_length=1024, description="Shown to each participant.")

    @field_validator("message", mode="after")
    @classmethod
    def _shown_text(cls, value: str | None) -> str | None:
        return None if value is None else message_text(value, "message")


class BulkApprovalView(BaseModel):
    """What a bulk approval did: each participant approved (or approved before), or refused
    with the reason; one refusal stops none of the others."""

    approved: list[int]
    refused: dict[int, str] = Field(description="Participant -> why their approval failed.")


class BonusRequest(Body):
    """Pay the participant a bonus for the submitted work."""

    amount: Annotated[Decimal, BeforeValidator(parse_amount)] = Field(
        description=f"In the platform's currency (US dollars on MTurk, the study's currency on "
        f'Prolific): 0.01 to {MAX_BONUS}, a number or a string like "1.50" (plain ASCII '
        "digits, at most two decimal places).",
    )
    reason: str = Field(min_length=1, max_length=1024, description="Shown to the participant.")
    unique_token: str = Field(
        pattern=r"^[A-Za-z0-9_\-]{8,64}$",
        description="Identifies this bonus: a retry with the same token pays nothing more "
        "(sent to MTurk as UniqueRequestToken).",
    )

    @field_validator("reason", mode="after")
    @classmethod
    def _shown_text(cls, value: str) -> str:
        return message_text(value, "reason")


class ReviewView(BaseModel):
    decision: ReviewDecision
    message: str | None
    rejection_category: str | None
    backend: str
    state: ReviewState = Field(description="pending: recorded, not yet confirmed by the platform.")
    decided_at: datetime | None


class BonusView(BaseModel):
    amount: str = Field(description="In ``currency``.")
    currency: str
    reason: str
    unique_token: str
    backend: str
    state: str = Field(
        description="paid; or pending, set_up, paying: recorded, not yet confirmed paid; or "
        "in_doubt: the platform's pay failed after it may have paid (Prolific: settled from the "
        "submission's bonus_payments by a resend or the reconciliation, never paid twice)."
    )
    setup_id: str | None = Field(description="Prolific's bonus set-up id.")
    pay_sent_at: datetime | None = Field(description="When Prolific's pay was sent.")
    paid_at: datetime | None
    note: str | None = Field(
        description="What an unsettled bonus waits for and how it settles (None once paid)."
    )


class StatusChangeView(BaseModel):
    status: str
    at: datetime
    note: str | None


class QueueView(BaseModel):
    """The learner updates' live queue beside the capacity (``server.app.capacity``)."""

    capacity: int | None = Field(
        description="Participants who can teach at once without waiting (none: not measured yet)."
    )
    update_seconds: float | None = Field(
        description="The measured wall time of one update (live, where the update processes "
        "share the server's cores: its CPU time)."
    )
    measured_on: str | None = Field(description="What the update time was measured on.")
    server_seconds_per_update: float | None = Field(
        description="The server process's own CPU seconds per update (a participant's requests "
        "between two updates, the update's reading and storing; once live, with a PostgreSQL "
        "server's on the same machine), which the capacity counts where the update processes "
        "share the server's cores (none: not counted)."
    )
    longest_update_seconds: float | None = Field(
        description="The longest update timed at start: an agent that follows one is ready "
        "that long after its episode ends, however few participants teach (none: not timed)."
    )
    longest_update_of: str | None = Field(
        description="The learner and environment of that update, as 'learner in environment'."
    )
    slots: int = Field(
        description="Updates the deployment runs at once (processes on their own cores, each "
        "machine's cores once, or a cluster's workers); this server's before its capacity is "
        "known."
    )
    update_interval_seconds: float = Field(
        description="How often a participant teaching queues an update (BAM_UPDATE_INTERVAL_SECONDS)."
    )
    limit: int | None = Field(description="Participants in the study at once (none: no limit yet).")
    limit_from: Literal["study file", "capacity"] | None
    participants_active: int = Field(description="In the study now (seen in BAM_ACTIVE_MINUTES).")
    participants_waiting: int = Field(description="Waiting for a place.")
    updates_pending: int = Field(description="Learner updates queued or running.")
    sessions_updating: int = Field(description="Sessions with an update running.")
    sessions_awaited: int = Field(description="Sessions whose agent someone waits for.")
    oldest_wait_seconds: float = Field(
        description="How long the longest of those waits has lasted."
    )
    updates_done: int = Field(description="Updates done since the server started.")


class AdminParticipant(BaseModel):
    participant_id: int
    platform: str
    platform_participant_id: str | None
    platform_submission_id: str | None
    platform_study_id: str | None
    status: str
    prolific_status: str | None = Field(
        None, description="Prolific's status of the submission (from its webhook or a poll)."
    )
    return_requested_at: datetime | None = Field(
        None,
        description="When Prolific asked the participant to return the submission (a "
        "completion code with REQUEST_RETURN, such as NO_CONSENT); returned only if "
        "prolific_status is RETURNED.",
    )
    awaits_decision: bool = Field(
        False,
        description="The work is open to approval or rejection: submitted, or on Prolific a "
        "decliner's completed submission or a finisher's timed-out one.",
    )
    auto_approval_at: datetime | None = Field(
        None,
        description="When the platform approves and pays the submission by itself unless "
        "someone decides first (Prolific: 21 days after it was completed, while AWAITING "
        "REVIEW).",
    )
    auto_approval_soon: bool = Field(
        False,
        description="auto_approval_at is at most 7 days away (AUTO_APPROVAL_WARNING_DAYS): "
        "the dashboard warns.",
    )
    domain: str | None
    excluded: bool
    exclusion_reason: str | None
    created_at: datetime
    last_seen_at: datetime
    minutes: float = Field(description="From arrival to completion, or to the last request.")
    agents_finished: int
    agents: int
    completion_code: str | None


class AdminSession(BaseModel):
    session_id: int
    participant_id: int
    kind: str
    position: int | None
    domain: str
    environment: str
    learner: str
    colour: str
    colour_hex: str = Field(description="The agent's colour as drawn on the page (#rrggbb).")
    status: str
    mode: str
    task: int
    started_at: datetime | None
    finished_at: datetime | None
    completed: bool
    episodes: int
    actions: int
    pending_updates: int
    final_normalized_return: float | None


class AdminParticipantDetail(AdminParticipant):
    status_changes: list[StatusChangeView]
    sessions: list[AdminSession]
    review: ReviewView | None = Field(None, description="The approval or rejection, if any.")
    bonuses: list[BonusView] = Field(default_factory=list)


class AdminEvaluation(BaseModel):
    update_index: int
    status: str
    episodes: int
    actions: int
    normalized_return: float | None
    seconds: float | None
    queued_at: datetime
    finished_at: datetime | None


class AdminEvent(BaseModel):
    event_id: int
    seq: int
    kind: str
    created_at: datetime
    task: int | None
    mode: str | None
    state: int | None
    action: int | None
    next_state: int | None
    feedback: int | None
    episode_index: int | None
    record: str | None
    stay_state: int | None
    episode_end: str | None


class AdminReplay(BaseModel):
    """What a replay needs: the session, its grid, the first state and every event."""

    session: AdminSession
    environment: dict[str, Any] = Field(description="The grid as the teaching page draws it.")
    start_state: int | None
    events: list[AdminEvent]


class ServerRow(BaseModel):
    """One ``bam-study serve`` process of the deployment, as its latest heartbeat says
    (``server.app.updates.servers``)."""

    name: str = Field(description="Its name in the claims on learner updates.")
    host: str
    pid: int
    started_at: datetime
    heartbeat_at: datetime
    stopped_at: datetime | None
    live: bool = Field(
        description="Not stopped, and its heartbeat is more recent than the update lease."
    )
    this_server: bool = Field(description="The server that answered this request.")
    update_slots: int
    updates_running: int
    updates_completed: int
    updates_failed: int
    participants_at_once: int | None = Field(description="Its capacity (none: not yet timed).")
    machine: str = Field(
        description="Where its update slots run: the machine's boot id and the cores the server "
        "may use, or the Dask cluster's scheduler; the deployment's capacity counts the cores of "
        "servers with the same one once."
    )
    cores: int | None = Field(
        description="The cores its update processes share with it (none: a cluster's workers)."
    )
    update_seconds: float | None = Field(
        description="The cost of an update its capacity was stated from (none: not yet timed)."
    )
    server_seconds: float | None = Field(
        description="Its own CPU seconds per update, counted in its capacity (none: not counted)."
    )
