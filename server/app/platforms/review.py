"""Review of submitted work: approve or reject an MTurk assignment, and pay a bonus.

The platform's side is one small interface, ``ReviewBackend``, whose methods mirror boto3's
MTurk client (``approve_assignment(AssignmentId=, RequesterFeedback=)``, ``reject_assignment``,
``send_bonus(WorkerId=, BonusAmount=, AssignmentId=, Reason=, UniqueRequestToken=)``). Two
implement it: the local replica (``ReplicaReviewBackend``, acting on its own assignments and
shown in its HIT view) and ``MTurkClientBackend``, a thin adapter over boto3's client
(``BAM_REVIEW_BACKEND=mturk``; boto3 is imported only then).

``review_submission`` and ``pay_bonus`` check the study's side (the participant submitted an
MTurk assignment; no decision yet; a bonus token not used for anything else), call the backend,
and record what it did in ``assignment_reviews`` and ``bonuses``. A refusal changes nothing.
"""

from __future__ import annotations

from dataclasses import dataclass
from decimal import Decimal
from typing import Any, Literal, Protocol

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError

from server.app.errors import ApiError, InvalidInput
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import AssignmentReview, Bonus, Participant, utcnow
from server.app.storage.replica_models import ReplicaAssignment, ReplicaBonus

Decision = Literal["approved", "rejected"]


class ReviewRefused(Exception):
    """The platform refused the request (MTurk's RequestError); nothing was done there."""


class ReviewUnavailable(Exception):
    """The platform could not be reached or failed (MTurk's ServiceFault, a network error)."""


class ReviewBackend(Protocol):
    """The platform's review operations, as boto3's MTurk client names them."""

    name: str

    def approve_assignment(self, assignment_id: str, feedback: str | None) -> None: ...

    def reject_assignment(self, assignment_id: str, feedback: str) -> None: ...

    def send_bonus(
        self, worker_id: str, assignment_id: str, amount: str, reason: str, unique_token: str
    ) -> None: ...


# -- the local replica ------------------------------------------------------------------------
class ReplicaReviewBackend:
    """The replica's side: an assignment is approved or rejected once, after it was submitted,
    and a bonus goes to the worker of a submitted assignment, once per UniqueRequestToken, as on
    MTurk."""

    name = "replica"

    def __init__(self, db: Database) -> None:
        self.db = db

    def _decide(self, assignment_id: str, status: Decision, feedback: str | None) -> None:
        with self.db.write() as s:
            row = self._latest(s, assignment_id)
            if row.status != "submitted":
                raise ReviewRefused(
                    f"assignment {assignment_id} is {row.status}: only a submitted assignment "
                    "can be approved or rejected"
                )
            row.status = status
            row.reviewed_at = utcnow()
            row.requester_feedback = feedback

    @staticmethod
    def _latest(s: Any, assignment_id: str) -> ReplicaAssignment:
        row = s.scalar(
            select(ReplicaAssignment)
            .where(ReplicaAssignment.assignment_id == assignment_id)
            .order_by(ReplicaAssignment.id.desc())
            .limit(1)
        )
        if row is None:
            raise ReviewRefused(f"the replica has no assignment {assignment_id}")
        assert isinstance(row, ReplicaAssignment)
        return row

    def approve_assignment(self, assignment_id: str, feedback: str | None) -> None:
        self._decide(assignment_id, "approved", feedback)

    def reject_assignment(self, assignment_id: str, feedback: str) -> None:
        self._decide(assignment_id, "rejected", feedback)

    def send_bonus(
        self, worker_id: str, assignment_id: str, amount: str, reason: str, unique_token: str
    ) -> None:
        try:
            with self.db.write() as s:
                row = self._latest(s, assignment_id)
                if row.worker_id != worker_id:
                    raise ReviewRefused(f"assignment {assignment_id} is not worker {worker_id}'s")
                if row.status not in ("submitted", "approved", "rejected"):
                    raise ReviewRefused(
                        f"assignment {assignment_id} is {row.status}: a bonus is paid for "
                        "submitted work"
                    )
                s.add(
                    ReplicaBonus(
                        assignment_id=assignment_id,
                        worker_id=worker_id,
                        amount=amount,
                        reason=reason,
                        unique_request_token=unique_token,
                        granted_at=utcnow(),
                    )
                )
        except IntegrityError:
            raise ReviewRefused(
                f"a bonus with UniqueRequestToken {unique_token} was already sent"
            ) from None


# -- boto3's MTurk client -------------------------------------------------------------------
class MTurkClientBackend:
    """boto3's MTurk client (or any object with its methods) behind ``ReviewBackend``."""

    name = "mturk"

    def __init__(self, client: Any) -> None:
        self.client = client

    def _call(self, method: str, **arguments: Any) -> None:
        try:
            getattr(self.client, method)(**arguments)
        except Exception as error:
            # botocore's ClientError carries MTurk's error code: RequestError is a refusal,
            # ServiceFault (and anything else: no connection, no credentials) a failure.
            response = getattr(error, "response", None)
            details = response.get("Error", {}) if isinstance(response, dict) else {}
            code, message = details.get("Code"), details.get("Message") or str(error)
            if code == "RequestError":
                raise ReviewRefused(f"MTurk refused {method}: {message}") from None
            raise ReviewUnavailable(f"MTurk's {method} failed: {message}") from None

    def approve_assignment(self, assignment_id: str, feedback: str | None) -> None:
        arguments: dict[str, Any] = {"AssignmentId": assignment_id}
        if feedback:
            arguments["RequesterFeedback"] = feedback
        self._call("approve_assignment", **arguments)

    def reject_assignment(self, assignment_id: str, feedback: str) -> None:
        self._call("reject_assignment", AssignmentId=assignment_id, RequesterFeedback=feedback)

    def send_bonus(
        self, worker_id: str, assignment_id: str, amount: str, reason: str, unique_token: str
    ) -> None:
        self._call(
            "send_bonus",
            WorkerId=worker_id,
            BonusAmount=amount,
            AssignmentId=assignment_id,
            Reason=reason,
            UniqueRequestToken=unique_token,
        )


def mturk_client(settings: Settings) -> Any:
    """boto3's MTurk client for ``BAM_MTURK_ENDPOINT_URL`` (credentials from boto3's usual
    places: ``AWS_ACCESS_KEY_ID``, ``~/.aws``, ...)."""
    try:
        import boto3  # type: ignore[import-not-found,unused-ignore]
    except ImportError:
        raise ApiError(
            503, "BAM_REVIEW_BACKEND=mturk needs the boto3 package: pip install boto3"
        ) from None
    return boto3.client(
        "mturk", region_name=settings.mturk_region, endpoint_url=settings.mturk_endpoint_url
    )


def make_backend(settings: Settings, db: Database) -> ReviewBackend:
    if settings.review_backend == "mturk":
        return MTurkClientBackend(mturk_client(settings))
    return ReplicaReviewBackend(db)


# -- the study's side -------------------------------------------------------------------------
@dataclass(frozen=True)
class Reviewed:
    """The participant's MTurk ids, checked for review."""

    participant_id: int
    worker_id: str
    assignment_id: str


def _reviewable(db: Database, participant_id: int) -> Reviewed:
    with db.read() as s:
        p = s.get(Participant, participant_id)
        if p is None:
            raise ApiError(404, f"no participant {participant_id}")
        if p.platform != "mturk" or not p.assignment_id or not p.worker_id:
            raise ApiError(
                409,
                f"participant {participant_id} came from {p.platform}, not from an MTurk "
                "assignment: there is nothing to approve, reject or pay a bonus for",
            )
        if p.status != "submitted":
            raise ApiError(
                409,
                f"participant {participant_id} has not submitted the assignment (status "
                f"{p.status}): only submitted work is reviewed",
            )
        return Reviewed(p.id, p.worker_id, p.assignment_id)


def _platform(call: Any) -> None:
    try:
        call()
    except ReviewRefused as error:
        raise ApiError(409, str(error)) from None
    except ReviewUnavailable as error:
        raise ApiError(502, str(error)) from None


def _record(db: Database, row: AssignmentReview | Bonus, conflict: str) -> None:
    """Store what the platform took; a request that raced this one is answered 409."""
    try:
        with db.write() as s:
            s.add(row)
    except IntegrityError:
        raise ApiError(409, conflict) from None


def review_submission(
    db: Database,
    backend: ReviewBackend,
    participant_id: int,
    decision: Decision,
    feedback: str | None,
) -> None:
    """Approve or reject the participant's submitted assignment, once."""
    who = _reviewable(db, participant_id)
    with db.read() as s:
        earlier = s.scalar(
            select(AssignmentReview.decision).where(
                AssignmentReview.participant_id == participant_id
            )
        )
    if earlier is not None:
        raise ApiError(
            409, f"assignment {who.assignment_id} was already {earlier}: a decision is final"
        )
    if decision == "rejected" and not feedback:
        raise InvalidInput(
            ("body", "feedback"), "a rejection needs feedback: MTurk shows the worker why"
        )
    if decision == "approved":
        _platform(lambda: backend.approve_assignment(who.assignment_id, feedback))
    else:
        _platform(lambda: backend.reject_assignment(who.assignment_id, feedback or ""))
    decided = AssignmentReview(
        participant_id=participant_id,
        assignment_id=who.assignment_id,
        worker_id=who.worker_id,
        decision=decision,
        feedback=feedback,
        backend=backend.name,
        decided_at=utcnow(),
    )
    _record(db, decided, f"assignment {who.assignment_id} was decided meanwhile")


def dollars(cents: int) -> str:
    """MTurk's BonusAmount: US dollars with two decimals."""
    return f"{cents // 100}.{cents % 100:02d}"


def pay_bonus(
    db: Database,
    backend: ReviewBackend,
    participant_id: int,
    amount: Decimal,
    reason: str,
    unique_token: str,
) -> bool:
    """Pay the participant's worker a bonus of ``amount`` US dollars; False (nothing paid) when
    this token already paid exactly this bonus (a retry), 409 when it paid another."""
    cents = int(amount * 100)
    who = _reviewable(db, participant_id)
    with db.read() as s:
        earlier = s.scalar(select(Bonus).where(Bonus.unique_token == unique_token))
    if earlier is not None:
        same = (earlier.participant_id, earlier.amount_cents, earlier.reason) == (
            participant_id,
            cents,
            reason,
        )
        if same:
            return False
        raise ApiError(409, f"the request token {unique_token} was used for another bonus")
    _platform(
        lambda: backend.send_bonus(
            who.worker_id, who.assignment_id, dollars(cents), reason, unique_token
        )
    )
    paid = Bonus(
        participant_id=participant_id,
        assignment_id=who.assignment_id,
        worker_id=who.worker_id,
        amount_cents=cents,
        reason=reason,
        unique_token=unique_token,
        backend=backend.name,
        paid_at=utcnow(),
    )
    _record(db, paid, f"the request token {unique_token} was used meanwhile")
    return True
