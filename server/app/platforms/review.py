"""Review of submitted work: approve or reject a participant's submission, and pay a bonus,
on the participant's platform (MTurk or Prolific, or the local replica of either), with every
money action carried out exactly once.

The platform's side is one interface, ``ReviewBackend``. The study's side is here, and it is
the same for every platform:

1. the request is checked (the participant submitted work on the backend's platform; the amount
   is a plain decimal with at most two places; message is plain text);
2. the intent is recorded in the database *before* the platform is called: a decision as a
   ``pending`` row of ``assignment_reviews``, a bonus as a ``pending`` row of ``bonuses`` with
   its request token (sent as MTurk's UniqueRequestToken). On Prolific, whose ``pay`` call is
   not idempotent, the bonus's set-up id is stored (``set_up``) before ``pay`` is called, and
   ``pay`` is called only by the request that moved the row from ``set_up`` to ``paying``;
3. the platform is called, and the row is settled (``done``, ``paid``).

A retry, a double click or a second tab with the same request finds the row: a settled one is
answered as it stands; an unsettled one (the platform failed, or the server died between the
call and the record) is reconciled from the platform: MTurk answers "already exists" for a
UniqueRequestToken it has paid, and a decision already taken shows in the submission's status.
A definite refusal by the platform removes the intent (nothing was done there).
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime, timedelta
from decimal import Decimal
from typing import Any, Literal, Protocol, get_args

from sqlalchemy import delete, select, update
from sqlalchemy.exc import IntegrityError

from server.app import platform_registry as registry
from server.app.errors import ApiError, InvalidInput
from server.app.storage.db import Database
from server.app.storage.models import AssignmentReview, Bonus, Participant, utcnow
from server.app.storage.vocabulary import (
    BonusState,
    ParticipantStatus,
    ReviewDecision,
    ReviewState,
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
    worker_id: str  # MTurk's workerId or Prolific's PROLIFIC_PID
    assignment_id: str  # MTurk's assignmentId or Prolific's submission id (SESSION_ID)
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


# -- input ------------------------------------------------------------------------------------
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


# -- the study's side -------------------------------------------------------------------------
def reviewable(db: Database, participant_id: int, platform: str) -> Reviewed:
    with db.read() as s:
        p = s.get(Participant, participant_id)
        if p is None:
            raise ApiError(404, f"no participant {participant_id}")
        if p.platform != platform or not p.assignment_id or not p.worker_id:
            raise ApiError(
                409,
                f"participant {participant_id} came from {p.platform}, not from a submission "
                f"on {platform}: there is nothing to approve, reject or pay a bonus for",
            )
        if p.status != ParticipantStatus.SUBMITTED:
            raise ApiError(
                409,
                f"participant {participant_id} has not submitted their work (status "
                f"{p.status}): only submitted work is reviewed",
            )
        return Reviewed(p.id, p.platform, p.worker_id, p.assignment_id, p.hit_id)


def _wait_for(db: Database, read: Callable[[Any], Any], settled: Callable[[Any], bool]) -> Any:
    """The row ``read`` finds, once ``settled`` (or as it is after ``SETTLE_WAIT_SECONDS``)."""
    deadline = time.monotonic() + SETTLE_WAIT_SECONDS
    while True:
        with db.read() as s:
            row = read(s)
        if row is None or settled(row) or time.monotonic() > deadline:
            return row
        time.sleep(0.1)


def review_submission(
    db: Database,
    backend: ReviewBackend,
    participant_id: int,
    decision: ReviewDecision,
    message: str | None,
    category: str | None = None,
) -> None:
    """Approve or reject the participant's submitted work, once: a repeat of the same decision
    answers as the first did; another decision is refused (409, a decision is final)."""
    who = reviewable(db, participant_id, backend.platform)
    if decision == ReviewDecision.REJECTED and not message:
        raise InvalidInput(
            ("body", "message"),
            "a rejection needs a message: the platform shows the participant why",
        )
    platform = registry.platform(backend.platform)
    if decision == ReviewDecision.REJECTED:
        platform.check_rejection(message, category)

    def read(s: Any) -> AssignmentReview | None:
        return s.scalar(
            select(AssignmentReview).where(AssignmentReview.participant_id == participant_id)
        )

    try:
        with db.write() as s:
            earlier = read(s)
            if earlier is None:
                s.add(
                    AssignmentReview(
                        participant_id=participant_id,
                        assignment_id=who.assignment_id,
                        worker_id=who.worker_id,
                        decision=decision,
                        message=message,
                        rejection_category=category,
                        backend=backend.name,
                        state=ReviewState.PENDING,
                        requested_at=utcnow(),
                    )
                )
            else:
                earlier_decision, earlier_state = earlier.decision, earlier.state
    except IntegrityError:  # a concurrent request recorded its intent first
        with db.read() as s:
            row = read(s)
            assert row is not None
            earlier, earlier_decision, earlier_state = row, row.decision, row.state
    if earlier is not None:
        if earlier_decision != decision:
            raise ApiError(
                409,
                f"submission {who.assignment_id} was already {earlier_decision}: a decision "
                "is final",
            )
        if earlier_state == ReviewState.DONE:
            return
        # A duplicate: let the request that holds the intent settle it, then reconcile.
        row = _wait_for(db, read, lambda r: r.state == ReviewState.DONE)
        if row is not None and row.state == ReviewState.DONE:
            return
    try:
        if decision == ReviewDecision.APPROVED:
            backend.approve(who, message)
        else:
            backend.reject(who, message or "", category)
    except ReviewRefused as refused:
        # Refused: perhaps because an earlier attempt of this very decision went through.
        try:
            now = backend.decision_of(who)
        except ReviewRefused:
            now = None
        except ReviewUnavailable as error:
            raise ApiError(502, f"{refused}; and then {error}") from None
        if now != decision:
            with db.write() as s:
                s.execute(
                    delete(AssignmentReview).where(
                        AssignmentReview.participant_id == participant_id,
                        AssignmentReview.state == ReviewState.PENDING,
                    )
                )
            raise ApiError(409, str(refused)) from None
    except ReviewUnavailable as error:
        raise ApiError(
            502,
            f"{error}. The decision is recorded as pending: send it again and it will be "
            "reconciled with the platform",
        ) from None
    with db.write() as s:
        s.execute(
            update(AssignmentReview)
            .where(
                AssignmentReview.participant_id == participant_id,
                AssignmentReview.state == ReviewState.PENDING,
            )
            .values(state=ReviewState.DONE, decided_at=utcnow())
        )
        status = platform.status_after(decision)
        if status is not None:
            # The platform's status of the submission is now ours (its sync says it again).
            s.execute(
                update(Participant)
                .where(Participant.id == participant_id)
                .values(platform_status=status)
            )


def pay_bonus(
    db: Database,
    backend: ReviewBackend,
    participant_id: int,
    amount: Decimal,
    reason: str,
    unique_token: str,
) -> bool:
    """Pay the participant a bonus of ``amount`` in the backend's currency, exactly once per
    ``unique_token``. True when this call paid it; False when it was paid before (a retry or a
    concurrent duplicate, answered with the stored bonus); 409 when the token was used for
    another bonus, or the platform refused; 502 when the platform failed (the intent stays and
    a retry with the same token settles it without paying twice)."""
    cents = int(amount * 100)
    who = reviewable(db, participant_id, backend.platform)

    def read(s: Any) -> Bonus | None:
        return s.scalar(select(Bonus).where(Bonus.unique_token == unique_token))

    def same(row: Bonus) -> bool:
        return (row.participant_id, row.amount_cents, row.reason) == (participant_id, cents, reason)

    try:
        with db.write() as s:
            earlier = read(s)
            if earlier is None:
                s.add(
                    Bonus(
                        participant_id=participant_id,
                        assignment_id=who.assignment_id,
                        worker_id=who.worker_id,
                        amount_cents=cents,
                        currency=backend.currency,
                        reason=reason,
                        unique_token=unique_token,
                        backend=backend.name,
                        state=BonusState.PENDING,
                        requested_at=utcnow(),
                    )
                )
            elif not same(earlier):
                raise ApiError(409, f"the request token {unique_token} was used for another bonus")
            elif earlier.state == BonusState.PAID:
                return False
    except IntegrityError:  # a concurrent request with this token recorded its intent first
        earlier = _wait_for(db, read, lambda r: r.state == BonusState.PAID)
        assert earlier is not None
        if not same(earlier):
            raise ApiError(
                409, f"the request token {unique_token} was used for another bonus"
            ) from None
        if earlier.state == BonusState.PAID:
            return False
    return _settle_bonus(db, backend, who, unique_token, money(cents), reason)


def _settle_bonus(
    db: Database, backend: ReviewBackend, who: Reviewed, token: str, amount: str, reason: str
) -> bool:
    """Carry out the recorded intent ``token`` on the platform and record that it was paid."""
    where = Bonus.unique_token == token
    with db.read() as s:
        row = s.scalar(select(Bonus).where(where))
        assert row is not None
        setup_id, state, requested_at = row.setup_id, row.state, row.requested_at
    if state == BonusState.PENDING and _token_forgotten(backend, requested_at):
        with db.write() as s:
            s.execute(
                update(Bonus)
                .where(where, Bonus.state == BonusState.PENDING)
                .values(state=BonusState.IN_DOUBT)
            )
        state = BonusState.IN_DOUBT
    if state == BonusState.IN_DOUBT:
        raise ApiError(
            409,
            f"bonus {token} was asked for at {requested_at:%Y-%m-%d %H:%M} UTC and its payment "
            f"is in doubt: {backend.name} no longer remembers its request token, so sending it "
            "again could pay it twice. Check the worker's bonuses on the platform; it is not "
            "sent again from here",
        )
    if state == BonusState.PENDING and not backend.repeat_pay_is_safe:
        try:
            made = backend.set_up_bonus(who, amount, reason)
        except ReviewRefused as refused:  # nothing was set up: the intent goes
            with db.write() as s:
                s.execute(delete(Bonus).where(where, Bonus.state == BonusState.PENDING))
            raise ApiError(409, str(refused)) from None
        except ReviewUnavailable as error:
            raise ApiError(502, f"{error}. Send the same request again (same token)") from None
        if made is None:
            raise ApiError(500, f"{backend.name} set up no bonus to pay")
        # Only the first set-up is stored (and so paid); a concurrent one is never paid.
        with db.write() as s:
            s.execute(
                update(Bonus)
                .where(where, Bonus.setup_id.is_(None))
                .values(setup_id=made, state=BonusState.SET_UP)
            )
            setup_id = s.scalar(select(Bonus.setup_id).where(where))
    if not backend.repeat_pay_is_safe:
        # The one request that moves the bonus from set_up to paying calls pay.
        with db.write() as s:
            claimed = s.scalar(
                update(Bonus)
                .where(where, Bonus.state == BonusState.SET_UP)
                .values(state=BonusState.PAYING)
                .returning(Bonus.id)
            )
        if claimed is None:
            row = _wait_for(db, lambda s: s.scalar(select(Bonus).where(where)), _is_paid)
            if row is not None and row.state == BonusState.PAID:
                return False
            raise ApiError(
                502,
                f"bonus {token} was sent to {backend.name} for payment (set-up {setup_id}) and "
                "its outcome is not known yet: it will not be paid again from here; check the "
                "bonus on the platform",
            )
    try:
        backend.pay_bonus(who, amount, reason, token, setup_id)
    except AlreadyDone:
        pass
    except ReviewRefused as refused:
        with db.write() as s:
            if backend.repeat_pay_is_safe:
                s.execute(delete(Bonus).where(where, Bonus.state == BonusState.PENDING))
            else:  # the set-up stands; a retry pays it
                s.execute(update(Bonus).where(where).values(state=BonusState.SET_UP))
        raise ApiError(409, str(refused)) from None
    except ReviewUnavailable as error:
        retry = (
            "send the same request again (same token): it will not pay twice"
            if backend.repeat_pay_is_safe
            else "it will not be paid again from here; check the bonus on the platform"
        )
        raise ApiError(502, f"{error}. The bonus is recorded as unsettled: {retry}") from None
    with db.write() as s:
        s.execute(update(Bonus).where(where).values(state=BonusState.PAID, paid_at=utcnow()))
    return True


# A bonus is treated as forgotten an hour before the platform forgets its token: clocks and the
# time a resend takes to arrive are not exact.
TOKEN_MARGIN = timedelta(hours=1)


def _token_forgotten(backend: ReviewBackend, requested_at: datetime) -> bool:
    memory = backend.token_memory
    return memory is not None and utcnow() - requested_at > memory - TOKEN_MARGIN


def _is_paid(row: Bonus) -> bool:
    return row.state == BonusState.PAID


def reconcile_bonuses(db: Database, backend: ReviewBackend) -> list[str]:
    """Settle the backend's unsettled bonuses that can be settled safely (those whose payment
    may be repeated: MTurk's, by their UniqueRequestToken, or Prolific's set up but never sent
    to ``pay``); the tokens settled."""
    with db.read() as s:
        rows = s.execute(
            select(Bonus.participant_id, Bonus.unique_token, Bonus.amount_cents, Bonus.reason)
            .where(
                Bonus.backend == backend.name,
                Bonus.state.in_((BonusState.PENDING, BonusState.SET_UP)),
            )
            .order_by(Bonus.id)
        ).all()
    settled = []
    for participant_id, token, cents, reason in rows:
        with db.read() as s:
            p = s.get(Participant, participant_id)
            assert p is not None and p.worker_id and p.assignment_id
            who = Reviewed(p.id, p.platform, p.worker_id, p.assignment_id, p.hit_id)
        try:
            _settle_bonus(db, backend, who, token, money(cents), reason)
        except ApiError:
            continue
        settled.append(token)
    return settled
