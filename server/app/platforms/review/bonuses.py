"""Paying a bonus exactly once per request token: the intent recorded (refused past the
study's budget, or beside a Prolific bonus in doubt), the platform called, and a bonus whose
outcome is unknown settled from the platform's record (``reconcile_bonuses``)."""

from __future__ import annotations

from datetime import datetime, timedelta
from decimal import Decimal
from typing import Any

from sqlalchemy import delete, func, select, update
from sqlalchemy.exc import IntegrityError

from server.app.errors import ApiError
from server.app.platforms.review.base import (
    AlreadyDone,
    ReviewBackend,
    Reviewed,
    ReviewRefused,
    ReviewUnavailable,
    _wait_for,
    money,
    reviewable,
)
from server.app.storage.db import Database
from server.app.storage.models import Bonus, Installation, Participant, utcnow
from server.app.storage.vocabulary import (
    BonusState,
)

# A Prolific pay still out after this was lost (the client gives up on a call after 30 s).
PAY_CALL_LIMIT = timedelta(minutes=2)


# Prolific pays a bonus "in the following minutes" after its 202: a bonus that its record does
# not list this long after its pay was sent was not paid.
PAY_SETTLES_WITHIN = timedelta(minutes=30)


UNSETTLED = ("pending", "set_up", "paying", "in_doubt")


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
                        platform_submission_id=who.platform_submission_id,
                        platform_participant_id=who.platform_participant_id,
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
                Bonus.platform_submission_id == row.platform_submission_id,
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
            assert p is not None and p.platform_participant_id and p.platform_submission_id
            who = Reviewed(
                p.id,
                p.platform,
                p.platform_participant_id,
                p.platform_submission_id,
                p.platform_study_id,
            )
        try:
            _settle_bonus(db, backend, who, token, money(cents), reason)
        except ApiError:
            continue
        with db.read() as s:
            if s.scalar(select(Bonus.state).where(Bonus.unique_token == token)) != "paid":
                continue  # a pay Prolific accepted and has not listed yet: still in doubt
        settled.append(token)
    return settled
