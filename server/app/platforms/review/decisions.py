"""Approving or rejecting a participant's submitted work, once: the intent recorded, the
platform called, the decision settled (or reconciled with the platform on a repeat)."""

from __future__ import annotations

from typing import Any

from sqlalchemy import delete, select, update
from sqlalchemy.exc import IntegrityError

from server.app import platform_registry as registry
from server.app.errors import ApiError, InvalidInput
from server.app.platforms.review.base import (
    ReviewBackend,
    Reviewed,
    ReviewRefused,
    ReviewUnavailable,
    _wait_for,
    reviewable,
)
from server.app.storage.db import Database
from server.app.storage.models import Participant, Review, utcnow
from server.app.storage.vocabulary import (
    ReviewDecision,
    ReviewState,
)


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
    if _already_done(db, backend, who, decision, message, category):
        return
    _send(db, backend, who, decision, message, category)
    with db.write() as s:
        s.execute(
            update(Review)
            .where(
                Review.participant_id == participant_id,
                Review.state == ReviewState.PENDING,
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


def _already_done(
    db: Database,
    backend: ReviewBackend,
    who: Reviewed,
    decision: ReviewDecision,
    message: str | None,
    category: str | None,
) -> bool:
    """Record the intent (a ``pending`` review) before the platform is called; True when the
    same decision was carried out already (by an earlier request, or by a concurrent one that
    held the intent and settled it meanwhile); 409 when another decision was recorded."""
    participant_id = who.participant_id

    def read(s: Any) -> Review | None:
        return s.scalar(select(Review).where(Review.participant_id == participant_id))

    try:
        with db.write() as s:
            earlier = read(s)
            if earlier is None:
                s.add(
                    Review(
                        participant_id=participant_id,
                        platform_submission_id=who.platform_submission_id,
                        platform_participant_id=who.platform_participant_id,
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
            # The platform refused it and that request took its intent back: this one records
            # its intent again, and asks the platform itself.
            return _already_done(db, backend, who, decision, message, category)
        earlier, earlier_decision, earlier_state = row, row.decision, row.state
    if earlier is None:
        return False
    if earlier_decision != decision:
        raise ApiError(
            409,
            f"submission {who.platform_submission_id} was already {earlier_decision}: "
            "a decision is final",
        )
    if earlier_state == ReviewState.DONE:
        return True
    # A duplicate: let the request that holds the intent settle it, then reconcile.
    row = _wait_for(db, read, lambda r: r.state == ReviewState.DONE)
    return row is not None and row.state == ReviewState.DONE


def _send(
    db: Database,
    backend: ReviewBackend,
    who: Reviewed,
    decision: ReviewDecision,
    message: str | None,
    category: str | None,
) -> None:
    """The decision sent to the platform. A refusal that the platform's own decision does not
    explain (an earlier attempt of this very decision went through) removes the intent (409);
    a platform that fails leaves it pending (502), for a resend to reconcile."""
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
                    delete(Review).where(
                        Review.participant_id == who.participant_id,
                        Review.state == ReviewState.PENDING,
                    )
                )
            raise ApiError(409, str(refused)) from None
    except ReviewUnavailable as error:
        raise ApiError(
            502,
            f"{error}. The decision is recorded as pending: send it again and it will be "
            "reconciled with the platform",
        ) from None
