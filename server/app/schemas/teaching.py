"""The teaching page's bodies: choosing a task and a mode, a demonstrated move, a feedback, and
what each request did (``RequestOutcome``) with the teaching session's state after it."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import (
    BaseModel,
    Field,
)

from server.app.schemas.base import EpisodeKind, Mode, Move, SeqRequest, SessionStatus
from server.app.schemas.participant import ParticipantBrief, SessionSummary


class TaskRequest(SeqRequest):
    task: int = Field(ge=0, le=1000, description="Index of the task in the environment.")


class ModeRequest(SeqRequest):
    mode: Mode


class MoveRequest(SeqRequest):
    action: Move = Field(description="The arrow pressed (STAY cannot be demonstrated).")


class FeedbackRequest(SeqRequest):
    feedback: Literal[1, -1] = Field(description="+1 (positive) or -1 (negative).")


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
