"""The participant's bodies outside the teaching page: the arrival from a platform's link, the
waiting line, the device check, consent, the tutorial, the attention checks between agents,
the questionnaire and the completion; the participant's state and the study's public texts."""

from __future__ import annotations

import re
from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from server.app.platform_registry import PlatformName, arrival_parameters
from server.app.schemas.base import (
    Body,
    CheckShown,
    Colour,
    Move,
    SeqRequest,
    SessionKind,
    SessionStatus,
    plain_text,
)


def _arrival_schema(schema: dict[str, Any], model: type) -> None:
    schema["properties"] = {
        name: {"type": "string", "pattern": pattern}
        for name, pattern in arrival_parameters().items()
    }
    schema["additionalProperties"] = False


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
