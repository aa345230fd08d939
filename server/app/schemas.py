"""Request and response bodies of the JSON API (Pydantic); the ORM models never leave the server.

Every request that changes something carries ``seq``, the participant's next sequence number
(``next_seq`` in every response): a retried request with the same ``seq`` and body is answered
with the stored response, a request out of order gets 409.

Over 500 lines: every body of the API is here and nowhere else, so that a name in the OpenAPI
schema is defined once (the routers import their bodies from here).
"""

from __future__ import annotations

import re
from datetime import datetime
from decimal import Decimal
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from server.app.platform_registry import PlatformName, arrival_parameters
from server.app.platforms.base import ID_PATTERN as ID_PATTERN
from server.app.platforms.review import MAX_BONUS, RejectionCategory, message_text, parse_amount
from server.app.storage import vocabulary as v

MAX_SEQ = 1_000_000_000

# The API's literals of the stored vocabularies (``storage.vocabulary``), member by member: the
# OpenAPI schema lists the same strings as the database holds (tests/app/test_schemas.py checks
# that each lists its whole vocabulary, or the part the API answers with).
Mode = Literal[v.Mode.IDLE, v.Mode.DEMONSTRATE, v.Mode.AGENT]
SessionKind = Literal[v.SessionKind.TUTORIAL, v.SessionKind.STUDY]
SessionStatus = Literal[v.SessionStatus.PENDING, v.SessionStatus.ACTIVE, v.SessionStatus.FINISHED]
EpisodeKind = Literal[v.EpisodeKind.DEMONSTRATION, v.EpisodeKind.AGENT]
# A check the page is shown: the one being taken, or its outcome (never a pending one).
CheckShown = Literal[v.CheckStatus.ACTIVE, v.CheckStatus.PASSED, v.CheckStatus.FAILED]
ReviewDecision = Literal[v.ReviewDecision.APPROVED, v.ReviewDecision.REJECTED]
ReviewState = Literal[v.ReviewState.PENDING, v.ReviewState.DONE]
Move = Literal["UP", "DOWN", "LEFT", "RIGHT"]


def plain_text(value: str) -> str:
    """Text the database stores as given: Unicode (no lone surrogate) without NUL, the same rule
    on SQLite and PostgreSQL (whose text cannot hold NUL)."""
    if "\x00" in value:
        raise ValueError("text must not contain NUL characters")
    try:
        value.encode("utf-8")
    except UnicodeEncodeError:
        raise ValueError("text must be valid Unicode (no lone surrogate)") from None
    return value


def _arrival_schema(schema: dict[str, Any], model: type) -> None:
    schema["properties"] = {
        name: {"type": "string", "pattern": pattern}
        for name, pattern in arrival_parameters().items()
    }
    schema["additionalProperties"] = False


class Body(BaseModel):
    """A request body: the JSON types documented (strict: no "1" for 1, no "yes" for true), no
    unknown field, text without NUL or lone surrogates."""

    model_config = ConfigDict(extra="forbid", strict=True)

    @field_validator("*", mode="after")
    @classmethod
    def _plain_text(cls, value: Any) -> Any:
        return plain_text(value) if isinstance(value, str) else value


class SeqRequest(Body):
    seq: int = Field(ge=1, le=MAX_SEQ, description="The participant's next sequence number.")


class ConsentRequest(SeqRequest):
    agree: bool


# What a browser may lack of what the study's pages use (the device check's report).
BrowserFeature = Literal["fetch", "dialog", "svg"]


class DeviceCheckRequest(SeqRequest):
    """What the page measured before consent: whether an arrow key was pressed in the time
    given, the window's size in CSS pixels, and what of the pages' needs the browser lacks."""

    arrow_key: bool = Field(description="An arrow key was pressed (false: none in the time).")
    width: int = Field(ge=0, le=100_000, description="window.innerWidth")
    height: int = Field(ge=0, le=100_000, description="window.innerHeight")
    missing: list[BrowserFeature] = Field(default_factory=list, max_length=3)


class TaskRequest(SeqRequest):
    task: int = Field(ge=0, le=1000, description="Index of the task in the environment.")


class ModeRequest(SeqRequest):
    mode: Mode


class MoveRequest(SeqRequest):
    action: Move = Field(description="The arrow pressed (STAY cannot be demonstrated).")


class TutorialStepRequest(SeqRequest):
    step: int = Field(ge=0, le=100, description="The tutorial step reached, from 0.")


class QuestionnaireRequest(SeqRequest):
    answers: dict[str, int | str] = Field(
        max_length=50,
        description="Question id -> answer: the text typed, the choice's text, or the Likert "
        "point (1 to the number of labels). An optional question may be left out.",
    )

    @field_validator("answers", mode="after")
    @classmethod
    def _plain_answers(cls, value: dict[str, int | str]) -> dict[str, int | str]:
        for answer in value.values():
            if isinstance(answer, str):
                plain_text(answer)
        return value


class FeedbackRequest(SeqRequest):
    feedback: Literal[1, -1] = Field(description="+1 (positive) or -1 (negative).")


class ArrivalRequest(Body):
    """The parameters the platform appends to the study URL (none for a lab participant): any
    platform's ``parameters`` (``server.app.platform_registry``), each a string matching its
    pattern."""

    model_config = ConfigDict(extra="allow", strict=True, json_schema_extra=_arrival_schema)
    __pydantic_extra__: dict[str, str | None] = Field(init=False)

    @model_validator(mode="after")
    def _parameters(self) -> ArrivalRequest:
        patterns = arrival_parameters()
        for name, value in self.params().items():
            where = {"parameter": name[:64]}
            if name not in patterns:
                raise PydanticCustomError(
                    "extra_forbidden",
                    "Extra inputs are not permitted: {parameter} is no platform's parameter",
                    where,
                )
            try:
                plain_text(value)
            except ValueError as error:
                raise PydanticCustomError("text", f"{{parameter}}: {error}", where) from None
            if not re.fullmatch(patterns[name], value):
                raise PydanticCustomError(
                    "string_pattern_mismatch",
                    "{parameter}: String should match pattern '{pattern}'",
                    {**where, "pattern": patterns[name]},
                )
        return self

    def params(self) -> dict[str, str]:
        """The parameters given (a null is a parameter not given)."""
        return {k: v for k, v in (self.__pydantic_extra__ or {}).items() if v is not None}


# -- responses ------------------------------------------------------------------------------
class ErrorMessage(BaseModel):
    """Every refusal but a 422 (whose detail lists the fields at fault)."""

    detail: str
    turned_away: bool | None = Field(None, description="The arrival is refused for good.")


ERROR_RESPONSES: dict[int | str, dict[str, Any]] = {
    status: {"model": ErrorMessage, "description": description}
    for status, description in {
        400: "A bad request (a bad link, a bad parameter).",
        401: "No participant or admin token, or an unknown one.",
        403: "Turned away (a repeat worker, or the wrong platform).",
        404: "No such participant or learning session.",
        409: "Not now: a sequence number out of order, or a step the flow is not at.",
        413: "The request body is too large.",
        429: "Too many failed sign-ins from this address: wait Retry-After seconds.",
        502: "The review backend (MTurk) could not be reached or failed; nothing was recorded.",
        503: "Not available: the admin token is not set, or the agent is still learning.",
    }.items()
}


class Colour(BaseModel):
    name: str
    hex: str


class PlaceView(BaseModel):
    """A waiting participant's place in line (``places``)."""

    admitted: bool = Field(description="In the study: load the study page again.")
    ahead: int = Field(description="Participants waiting before this one.")
    active: int = Field(description="Participants in the study now.")
    limit: int | None = Field(description="Participants in the study at once (none: no limit).")
    ask_seconds: int = Field(description="Ask again after this long.")


class Completion(BaseModel):
    """How the participant finishes, issued once the completion is committed."""

    code: str
    mode: PlatformName
    submit_url: str | None = Field(None, description="MTurk: POST the fields here, from the top.")
    submit_fields: dict[str, str] | None = None
    redirect_url: str | None = Field(None, description="Prolific: send the participant here.")


class ParticipantBrief(BaseModel):
    status: str
    current_session_id: int | None
    next_seq: int
    completion: Completion | None = None


class SessionSummary(BaseModel):
    session_id: int
    kind: SessionKind
    position: int | None = Field(description="0.. among the study's agents; None: tutorial.")
    domain: str
    environment: str
    colour: Colour
    status: SessionStatus
    opened: bool = Field(description="The participant began teaching it (past its introduction).")


class Progress(BaseModel):
    agent: int = Field(description="Study agents finished or being taught (1-based).")
    of: int


class AttentionCheckView(BaseModel):
    """An instructional attention check: move the robot to the star on an open grid."""

    number: int = Field(description="1.. among the participant's checks.")
    of: int = Field(description="The participant's checks.")
    size: int = Field(description="The grid's width and height, in cells.")
    robot: tuple[int, int] = Field(description="Where the robot is: [row, column].")
    star: tuple[int, int] = Field(description="Where the star is: [row, column].")
    moves_made: int
    moves_allowed: int
    status: CheckShown


class AttentionMoveRequest(SeqRequest):
    action: Move = Field(description="The arrow pressed.")


class AttentionOutcome(BaseModel):
    """The answer to a move in an attention check: the check after it and where the
    participant is (the next agent once the check is over)."""

    seq: int
    kind: str
    check: AttentionCheckView
    participant: ParticipantBrief


class ParticipantState(ParticipantBrief):
    participant_id: int
    platform: PlatformName
    domain: str | None
    progress: Progress
    sessions: list[SessionSummary]
    tutorial_step: int = Field(description="The tutorial step reached, from 0.")
    attention_check: AttentionCheckView | None = Field(
        None, description="The attention check being taken, if any (between two agents)."
    )


class ArrivalResponse(BaseModel):
    preview: bool = False
    token: str | None = Field(None, description="Also set as an HttpOnly cookie.")
    resumed: bool = False
    participant: ParticipantState | None = None


class EpisodeState(BaseModel):
    index: int
    kind: EpisodeKind
    task: int
    actions: int


class Learning(BaseModel):
    pending: int = Field(description="Updates queued or running: the agent is learning.")
    updates: int = Field(
        description="Updates after episodes finished (done or failed), counted as sessions.csv's "
        "`updates`: the untrained learner's evaluation (update 0) is not one of them."
    )


class TeachingState(BaseModel):
    session_id: int
    status: SessionStatus
    task: int
    mode: Mode
    agent: dict[str, Any] | None = Field(description="The agent's cell and feature.")
    episode: EpisodeState | None
    episodes: int
    actions: int
    demonstrated: list[int] = Field(description="Demonstrated actions per task.")
    can_finish: bool
    finish_blocked: str | None = Field(description="Why this agent cannot be finished yet.")
    can_give_feedback: bool
    learning: Learning


class Outcome(BaseModel):
    """What one request did."""

    state: int | None = None
    action: str | None = None
    next_state: int | None = None
    feedback: int | None = None
    episode_ended: str | None = Field(None, description="Why an episode ended, if one did.")
    goal_reached: bool = False
    new_start: bool = Field(
        False,
        description="The agent stood on the selected task's goal with a mode on: it was put at "
        "a random start of the task (from state to next_state) before any episode began.",
    )
    update_queued: int | None = None
    learning_wait_seconds: float | None = None


class RequestOutcome(BaseModel):
    """The answer to a request that changes something: its outcome and the state after it."""

    seq: int
    kind: str
    outcome: Outcome
    session: TeachingState | None
    participant: ParticipantBrief


class SessionView(BaseModel):
    summary: SessionSummary
    environment: dict[str, Any] = Field(description="Static drawing description of the grid.")
    teaching: TeachingState
    participant: ParticipantBrief


class PublicStudy(BaseModel):
    title: str
    consent: str
    payment: str
    completion_mode: str
    tutorial: bool
    agents_per_environment: int
    reveal_gravity: bool
    environments: list[str] = Field(
        description="The environments the study teaches, tutorials included, by name (a "
        "simulated teacher must know each: `bam-study teach --study` gives it the study's own)."
    )
    questionnaire: dict[str, Any] | None = Field(
        None, description="The post-study questionnaire (intro and questions); None: none."
    )
    device_check: dict[str, Any] | None = Field(
        None,
        description="The device check before consent (min_width, min_height, key_seconds); "
        "None: none.",
    )


# -- admin ----------------------------------------------------------------------------------
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
    worker_id: str | None
    assignment_id: str | None
    hit_id: str | None
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
    last_normalized_return: float | None


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
