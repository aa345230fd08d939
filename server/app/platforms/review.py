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

A Prolific bonus whose ``pay`` was sent and not answered 2xx (a 429, a time-out, a 5xx, a
refusal, or the server dying while it was out) may have been paid: it is ``in_doubt``, and only
Prolific's record settles it. The submission's ``bonus_payments`` (GET /submissions/{id}/) lists
the bonuses paid on it: a bonus it lists is ``paid``; one it does not list, once Prolific has had
``PAY_SETTLES_WITHIN`` to carry out an asynchronous pay, was not paid, goes back to ``set_up``
and is paid again, once. A resend of the bonus (same token) or the reconciliation settles it;
until then no new bonus for that participant is taken, so that a fresh form cannot pay it twice.
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime, timedelta
from decimal import Decimal
from typing import Any, Literal, Protocol, get_args

from sqlalchemy import delete, func, select, update
from sqlalchemy.exc import IntegrityError

from server.app import platform_registry as registry
from server.app.errors import ApiError, InvalidInput
from server.app.storage.db import Database
from server.app.storage.models import AssignmentReview, Bonus, Installation, Participant, utcnow
from server.app.storage.vocabulary import (
    BonusState,
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
# A Prolific pay still out after this was lost (the client gives up on a call after 30 s).
PAY_CALL_LIMIT = timedelta(minutes=2)
# Prolific pays a bonus "in the following minutes" after its 202: a bonus that its record does
# not list this long after its pay was sent was not paid.
PAY_SETTLES_WITHIN = timedelta(minutes=30)
UNSETTLED = ("pending", "set_up", "paying", "in_doubt")


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

    def bonuses_paid(self, who: Reviewed) -> list[int] | None:
        """The bonuses the platform lists as paid on the submission, in cents (Prolific's
        ``bonus_payments``); None where it keeps no such record to settle a bonus by."""
        ...


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
def reviewable(
    db: Database, participant_id: int, platform: str, decision: bool = False
) -> Reviewed:
    """The participant's ids, checked: from ``platform``, with submitted work (for a
    ``decision``, work the platform says is open to one: ``Platform.awaits_decision``)."""
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
    who = reviewable(db, participant_id, backend.platform, decision=True)
    if decision == "rejected" and not message:
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
        if row is None:
            # The platform refused it and that request took its intent back: this one asks
            # again, and answers what the platform says.
            return review_submission(db, backend, participant_id, decision, message, category)
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
    budget_cents: int | None = None,
) -> bool:
    """Pay the participant a bonus of ``amount`` in the backend's currency, exactly once per
    ``unique_token``. True when this call paid it; False when it was paid before (a retry or a
    concurrent duplicate, answered with the stored bonus); 409 when the token was used for
    another bonus, the platform refused, the bonus would take the study's bonuses past
    ``budget_cents`` (nothing is recorded or sent), or the participant has a Prolific bonus in
    doubt (settle it first); 502 when the platform failed (the intent stays and a retry with
    the same token settles it without paying twice)."""
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
                if not backend.repeat_pay_is_safe:
                    _refuse_beside_doubt(s, backend, participant_id)
                if budget_cents is not None:
                    _check_budget(s, backend, cents, budget_cents)
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
        if earlier is None:
            # The platform refused it and that request took its intent back: this one asks
            # again, and answers what the platform says (its refusal, a 409, most likely).
            return pay_bonus(
                db, backend, participant_id, amount, reason, unique_token, budget_cents
            )
        if not same(earlier):
            raise ApiError(
                409, f"the request token {unique_token} was used for another bonus"
            ) from None
        if earlier.state == BonusState.PAID:
            return False
    return _settle_bonus(db, backend, who, unique_token, money(cents), reason)


def _refuse_beside_doubt(s: Any, backend: ReviewBackend, participant_id: int) -> None:
    """409 when the participant has a bonus whose pay may have paid (``paying``, ``in_doubt``):
    a new request token for it (a reloaded form) could pay it a second time."""
    doubtful = s.scalar(
        select(Bonus)
        .where(
            Bonus.participant_id == participant_id,
            Bonus.backend == backend.name,
            Bonus.state.in_(("paying", "in_doubt")),
        )
        .limit(1)
    )
    if doubtful is not None:
        raise ApiError(
            409,
            f"participant {participant_id} has a bonus of {money(doubtful.amount_cents)} "
            f"{doubtful.currency} whose payment is in doubt (request token "
            f"{doubtful.unique_token}): settle it first (send it again with its own token, or "
            "reconcile), so that a new request cannot pay it a second time",
        )


def _check_budget(s: Any, backend: ReviewBackend, cents: int, budget_cents: int) -> None:
    """409 when ``cents`` would take the bonuses recorded on the backend (paid, or perhaps paid)
    past ``budget_cents``; nothing is recorded then."""
    # One bonus at a time passes this check (PostgreSQL: the installation's row is locked;
    # SQLite runs one write at a time).
    s.execute(select(Installation.id).with_for_update())
    spent = int(
        s.scalar(
            select(func.coalesce(func.sum(Bonus.amount_cents), 0)).where(
                Bonus.backend == backend.name
            )
        )
        or 0
    )
    if spent + cents > budget_cents:
        raise ApiError(
            409,
            f"a bonus of {money(cents)} {backend.currency} would take the study's bonuses to "
            f"{money(spent + cents)}, past its budget of {money(budget_cents)} (the study "
            f"file's bonus_budget); {money(max(budget_cents - spent, 0))} is left. Nothing "
            "was paid",
        )


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
            s.execute(update(Bonus).where(where, Bonus.state == "pending").values(state="in_doubt"))
        state = "in_doubt"
    if state == "in_doubt" and backend.repeat_pay_is_safe:
        raise ApiError(
            409,
            f"bonus {token} was asked for at {requested_at:%Y-%m-%d %H:%M} UTC and its payment "
            f"is in doubt: {backend.name} no longer remembers its request token, so sending it "
            "again could pay it twice. Check the worker's bonuses on the platform; it is not "
            "sent again from here",
        )
    if state in ("paying", "in_doubt"):
        # Prolific's pay was sent: only Prolific's record says whether it paid.
        if _settle_from_record(db, backend, who, token):
            return False
        state = "set_up"  # not paid: its set-up is paid now, once
    if state == "pending" and not backend.repeat_pay_is_safe:
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
    if not backend.repeat_pay_is_safe:
        # The one request that moves the bonus from set_up to paying calls pay.
        with db.write() as s:
            claimed = s.scalar(
                update(Bonus)
                .where(where, Bonus.state == "set_up")
                .values(state="paying", pay_sent_at=utcnow())
                .returning(Bonus.setup_id)
            )
        if claimed is None:
            with db.read() as s:
                row = s.scalar(select(Bonus).where(where))
            if row is not None and row.state == "paid":
                return False
            raise ApiError(409, _unsettled_message(row, token))
        setup_id = claimed
    try:
        backend.pay_bonus(who, amount, reason, token, setup_id)
    except AlreadyDone:
        pass
    except (ReviewRefused, ReviewUnavailable) as error:
        if backend.repeat_pay_is_safe:
            if isinstance(error, ReviewUnavailable):
                raise ApiError(
                    502,
                    f"{error}. The bonus is recorded as unsettled: send the same request again "
                    "(same token): it will not pay twice",
                ) from None
            with db.write() as s:
                s.execute(delete(Bonus).where(where, Bonus.state == "pending"))
            raise ApiError(409, str(error)) from None
        # Prolific's pay was sent and is not idempotent: it may have paid (a 429 or an error
        # after paying, an answer lost on the way).
        with db.write() as s:
            s.execute(update(Bonus).where(where, Bonus.state == "paying").values(state="in_doubt"))
            row = s.scalar(select(Bonus).where(where))
        status = 502 if isinstance(error, ReviewUnavailable) else 409
        raise ApiError(status, f"{error}. {_unsettled_message(row, token)}") from None
    if not backend.repeat_pay_is_safe:
        # Prolific's pay answers 202 and pays asynchronously: accepted is not paid. The
        # submission's bonus_payments settles it, now if it lists the bonus already, else
        # later (a resend or the reconciliation), as a bonus in doubt; never by paying again
        # before Prolific has had PAY_SETTLES_WITHIN to pay it.
        with db.write() as s:
            s.execute(update(Bonus).where(where, Bonus.state == "paying").values(state="in_doubt"))
        try:
            return _settle_from_record(db, backend, who, token)
        except ApiError:
            return False  # in doubt until Prolific's record lists it
    with db.write() as s:
        s.execute(update(Bonus).where(where).values(state=BonusState.PAID, paid_at=utcnow()))
    return True


def _sent_at(row: Any) -> datetime:
    """When the bonus's pay was sent (before this was kept: when it was paid or asked for)."""
    return row.pay_sent_at or row.paid_at or row.requested_at  # type: ignore[no-any-return]


def _settle_from_record(db: Database, backend: ReviewBackend, who: Reviewed, token: str) -> bool:
    """Settle the bonus ``token`` whose pay was sent (``paying`` or ``in_doubt``) from the
    platform's record of the submission's bonuses: True (now ``paid``) when the record lists
    it; False (now ``set_up``, to be paid again) when it does not, ``PAY_SETTLES_WITHIN`` after
    every pay of that amount to the submission was sent; else 409 (still in doubt).

    The record lists amounts, not set-ups, so a bonus is matched by its amount among the bonuses
    of that amount sent to the submission: the ones answered 2xx (``paid``) account for as many
    entries of the record, the doubtful ones for the rest, oldest first (a bonus paid by hand on
    Prolific's site is taken for one of ours: a bonus is left unpaid, never paid twice)."""
    where = Bonus.unique_token == token
    now = utcnow()
    with db.read() as s:
        row = s.scalar(select(Bonus).where(where))
        assert row is not None
        if row.state == "paying" and now - _sent_at(row) < PAY_CALL_LIMIT:
            raise ApiError(409, _unsettled_message(row, token))
        sent = s.execute(
            select(Bonus.id, Bonus.state, Bonus.pay_sent_at, Bonus.paid_at, Bonus.requested_at)
            .where(
                Bonus.assignment_id == row.assignment_id,
                Bonus.backend == row.backend,
                Bonus.amount_cents == row.amount_cents,
                Bonus.state.in_(("paid", "paying", "in_doubt")),
            )
            .order_by(Bonus.id)
        ).all()
    try:
        listed = backend.bonuses_paid(who)
    except ReviewRefused as refused:
        raise ApiError(409, f"{refused}. {_unsettled_message(row, token)}") from None
    except ReviewUnavailable as error:
        raise ApiError(502, f"{error}. {_unsettled_message(row, token)}") from None
    if listed is None:
        raise ApiError(
            409,
            f"bonus {token}'s payment is in doubt and {backend.name} keeps no record of a "
            "submission's bonuses to settle it by: check it on the platform; it is not sent "
            "again from here",
        )
    on_record = sum(1 for cents in listed if round(cents) == row.amount_cents)
    confirmed = sum(1 for r in sent if r.state == "paid")
    doubtful = [r.id for r in sent if r.state != "paid"]
    if row.id not in doubtful:
        # Settled by a concurrent request between the two reads (PostgreSQL's read committed
        # lets each statement see what committed meanwhile): answer as it left it.
        return _as_settled(db, where, token)
    # The 2xx ones will all be on the record: at least this many doubtful ones were paid.
    if doubtful.index(row.id) < on_record - confirmed:
        paid = True
    elif now < max(_sent_at(r) for r in sent) + PAY_SETTLES_WITHIN:
        raise ApiError(409, _unsettled_message(row, token, on_record=False))
    else:
        paid = False
    # Only the state read above is settled: a concurrent request that settled it first and
    # sent pay again (a new pay_sent_at) is not undone.
    same = (
        Bonus.pay_sent_at.is_(None)
        if row.pay_sent_at is None
        else Bonus.pay_sent_at == row.pay_sent_at
    )
    with db.write() as s:
        done = s.scalar(
            update(Bonus)
            .where(where, Bonus.state == row.state, same)
            .values(
                {"state": "paid", "paid_at": _sent_at(row)}
                if paid
                else {"state": "set_up", "pay_sent_at": None}
            )
            .returning(Bonus.id)
        )
    if done is None:
        return _as_settled(db, where, token)
    return paid


def _as_settled(db: Database, where: Any, token: str) -> bool:
    """A bonus another request settled first: True where it is paid now, else 409 saying
    what it waits for."""
    with db.read() as s:
        now_row = s.scalar(select(Bonus).where(where))
    if now_row is not None and now_row.state == "paid":
        return True
    raise ApiError(409, _unsettled_message(now_row, token))


def _unsettled_message(row: Any, token: str, on_record: bool | None = None) -> str:
    """What an unsettled Prolific bonus is waiting for, in words."""
    if row is None:
        return f"bonus {token} is no longer recorded"
    state = row.state
    if state == "paying" and utcnow() - _sent_at(row) < PAY_CALL_LIMIT:
        return (
            f"bonus {token} is being paid now (Prolific's pay was sent at "
            f"{_sent_at(row):%H:%M:%S} UTC): look again in a minute; it is not sent twice"
        )
    if state in ("paying", "in_doubt"):
        sent, after = _sent_at(row), _sent_at(row) + PAY_SETTLES_WITHIN
        listed = (
            "Prolific does not list it among the submission's bonuses yet"
            if on_record is False
            else "It is settled from Prolific's record of the submission's bonuses"
        )
        return (
            f"bonus {token} is in doubt: Prolific's pay was sent at {sent:%Y-%m-%d %H:%M} UTC "
            f"and may have paid. {listed}: paid if Prolific lists it; if not, paid again from "
            f"here, once, from {after:%H:%M} UTC (Prolific pays within minutes). Send it again "
            "(same token) or reconcile to settle it: it is never paid twice"
        )
    return f"bonus {token} is {state}: send it again (same token) to pay it"


def bonus_note(row: Bonus) -> str | None:
    """The bonus's state in words for the dashboard (None once paid)."""
    if row.state == "paid":
        return None
    if row.state == "in_doubt" and not row.backend.startswith("prolific"):
        return (
            "in doubt: unsettled for longer than the platform remembers its request token; "
            "check it on the platform (it is not sent again from here)"
        )
    if row.state in ("paying", "in_doubt"):
        return _unsettled_message(row, row.unique_token)
    return "recorded, not yet paid: send it again (same token) or reconcile to pay it"


# A bonus is treated as forgotten an hour before the platform forgets its token: clocks and the
# time a resend takes to arrive are not exact.
TOKEN_MARGIN = timedelta(hours=1)


def _token_forgotten(backend: ReviewBackend, requested_at: datetime) -> bool:
    memory = backend.token_memory
    return memory is not None and utcnow() - requested_at > memory - TOKEN_MARGIN


def reconcile_bonuses(db: Database, backend: ReviewBackend) -> list[str]:
    """Settle the backend's unsettled bonuses that can be settled safely (those whose payment
    may be repeated: MTurk's, by their UniqueRequestToken, or Prolific's set up but never sent
    to ``pay``; and Prolific's in doubt, from its record of the submission's bonuses); the
    tokens settled."""
    states = ("pending", "set_up") if backend.repeat_pay_is_safe else UNSETTLED
    with db.read() as s:
        rows = s.execute(
            select(Bonus.participant_id, Bonus.unique_token, Bonus.amount_cents, Bonus.reason)
            .where(Bonus.backend == backend.name, Bonus.state.in_(states))
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
        with db.read() as s:
            if s.scalar(select(Bonus.state).where(Bonus.unique_token == token)) != "paid":
                continue  # a pay Prolific accepted and has not listed yet: still in doubt
        settled.append(token)
    return settled
