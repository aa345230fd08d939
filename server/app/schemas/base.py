"""What every body of the API shares: the request base (``Body``, strict JSON, text without NUL
or lone surrogates), the sequence number (``SeqRequest``), the literals of the stored
vocabularies, and the error body of every refusal (``ERROR_RESPONSES``)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    field_validator,
)

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
