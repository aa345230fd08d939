"""What the decisions and the bonuses share: the platform's side (``ReviewBackend`` and its
refusals), the checks of the request (the amount, the text shown, the participant's submitted
work), and the wait for a concurrent request to settle its intent."""

from __future__ import annotations

import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import timedelta
from decimal import Decimal
from typing import Any, Literal, Protocol, get_args

from server.app import platform_registry as registry
from server.app.errors import ApiError
from server.app.storage.db import Database
from server.app.storage.models import Participant
from server.app.storage.vocabulary import (
    ReviewDecision,
)

# The largest bonus the dashboard pays at once, in the study's currency (docs/running-a-study.md).
MAX_BONUS = Decimal(100)


AMOUNT = re.compile(r"[0-9]{1,6}(\.[0-9]{1,2})?")


CONTROL = re.compile(r"[\x00-\x08\x0b\x0c\x0e-\x1f\x7f-\x9f]")


# Prolific's rejection categories (POST /submissions/{id}/transition/ with action REJECT).
RejectionCategory = Literal[
    "TOO_QUICKLY",
    "TOO_SLOWLY",
    "FAILED_INSTRUCTIONS",
    "INCOMP_LONGITUDINAL",
    "FAILED_CHECK",
    "LOW_EFFORT",
    "MALINGERING",
    "NO_CODE",
    "BAD_CODE",
    "NO_DATA",
    "UNSUPP_DEVICE",
    "OTHER",
]


REJECTION_CATEGORIES: tuple[str, ...] = get_args(RejectionCategory)


# Prolific refuses a rejection message shorter than this.
PROLIFIC_MIN_MESSAGE = 100


# How long a duplicate request waits for the request that holds the intent to settle it.
SETTLE_WAIT_SECONDS = 20.0


class ReviewRefused(Exception):
    """The platform refused the request (MTurk's RequestError, Prolific's 4xx): nothing was
    done there."""


class AlreadyDone(ReviewRefused):
    """The platform refused because this very request was already carried out (MTurk's answer
    to a UniqueRequestToken it has seen): the money action did happen."""


class ReviewUnavailable(Exception):
    """The platform could not be reached or failed (a 5xx, a dropped connection): the request
    may or may not have been carried out."""


@dataclass(frozen=True)
class Reviewed:
    """The participant's ids on their platform, checked for review."""

    participant_id: int
    platform: str  # mturk or prolific
    platform_participant_id: str  # MTurk's workerId or Prolific's PROLIFIC_PID
    platform_submission_id: str  # MTurk's assignmentId or Prolific's submission id (SESSION_ID)
    study_id: str | None  # MTurk's hitId or Prolific's STUDY_ID


class ReviewBackend(Protocol):
    """One platform's review operations."""

    name: str  # recorded with each decision and bonus: mturk, mturk-replica, prolific, ...
    platform: str  # the participants it reviews: mturk or prolific
    currency: str  # of its bonuses
    # False when paying a bonus twice pays twice (Prolific's ``pay``): then it is called once.
    repeat_pay_is_safe: bool
    # Where paying again is safe only while the platform remembers the request token (MTurk:
    # 24 hours), for how long; a bonus older than that is never sent again from here.
    token_memory: timedelta | None

    def approve(self, who: Reviewed, message: str | None) -> None: ...

    def reject(self, who: Reviewed, message: str, category: str | None) -> None: ...

    def decision_of(self, who: Reviewed) -> ReviewDecision | None:
        """The platform's decision on the submission now (None: not decided)."""
        ...

    def set_up_bonus(self, who: Reviewed, amount: str, reason: str) -> str | None:
        """Prepare the bonus on the platform without paying it: its id (None: no such step)."""
        ...

    def pay_bonus(
        self, who: Reviewed, amount: str, reason: str, token: str, setup_id: str | None
    ) -> None: ...

    def bonuses_paid(self, who: Reviewed) -> list[int] | None:
        """The bonuses the platform lists as paid on the submission, in cents (Prolific's
        ``bonus_payments``); None where it keeps no such record to settle a bonus by."""
        ...


def parse_amount(value: Any) -> Decimal:
    """A bonus amount: a JSON number or a string of a plain decimal with at most two places,
    ASCII digits only (no "1_0", no exponent, no Arabic-Indic or full-width digits), more than
    zero and at most ``MAX_BONUS``."""
    if isinstance(value, bool) or not isinstance(value, (str, int, float, Decimal)):
        raise ValueError("must be a number or a string like 1.50")
    text = repr(value) if isinstance(value, float) else str(value)
    if not AMOUNT.fullmatch(text):
        raise ValueError(
            f"must be a plain decimal with at most two places, like 1.50 (got {text[:20]!r})"
        )
    amount = Decimal(text)
    if not Decimal("0.01") <= amount <= MAX_BONUS:
        raise ValueError(f"must be from 0.01 to {MAX_BONUS}")
    return amount


def message_text(value: str, what: str) -> str:
    """Text shown to a participant: not blank, no control characters (newlines and tabs are
    allowed)."""
    if not value.strip():
        raise ValueError(f"{what} must not be blank")
    if CONTROL.search(value):
        raise ValueError(f"{what} must not contain control characters")
    return value


def money(cents: int) -> str:
    """An amount with two decimals, as MTurk's BonusAmount and Prolific's bonus CSV take it."""
    return f"{cents // 100}.{cents % 100:02d}"


dollars = money


def reviewable(
    db: Database, participant_id: int, platform: str, decision: bool = False
) -> Reviewed:
    """The participant's ids, checked: from ``platform``, with submitted work (for a
    ``decision``, work the platform says is open to one: ``Platform.awaits_decision``)."""
    with db.read() as s:
        p = s.get(Participant, participant_id)
        if p is None:
            raise ApiError(404, f"no participant {participant_id}")
        if p.platform != platform or not p.platform_submission_id or not p.platform_participant_id:
            raise ApiError(
                409,
                f"participant {participant_id} came from {p.platform}, not from a submission "
                f"on {platform}: there is nothing to approve, reject or pay a bonus for",
            )
        theirs = registry.platform(p.platform)
        if not (theirs.awaits_decision(p) if decision else p.status == "submitted"):
            if p.status == "submitted":  # the platform's status closed it
                raise ApiError(
                    409,
                    f"participant {participant_id}'s submission is {p.platform_status} on "
                    f"{theirs.display_name}: it is not open to review",
                )
            also = f", {theirs.display_name}'s {p.platform_status}" if p.platform_status else ""
            raise ApiError(
                409,
                f"participant {participant_id} has not submitted their work (status "
                f"{p.status}{also}): only submitted work is reviewed",
            )
        return Reviewed(
            p.id,
            p.platform,
            p.platform_participant_id,
            p.platform_submission_id,
            p.platform_study_id,
        )


def _wait_for(db: Database, read: Callable[[Any], Any], settled: Callable[[Any], bool]) -> Any:
    """The row ``read`` finds, once ``settled`` (or as it is after ``SETTLE_WAIT_SECONDS``)."""
    deadline = time.monotonic() + SETTLE_WAIT_SECONDS
    while True:
        with db.read() as s:
            row = read(s)
        if row is None or settled(row) or time.monotonic() > deadline:
            return row
        time.sleep(0.1)
