"""Mechanical Turk: the platform (``MTURK``: its link's parameters, the externalSubmit form, the
replica's rows), and behind ``ReviewBackend`` boto3's MTurk client (``BAM_REVIEW_BACKEND=mturk``;
boto3 is imported only then) and the local replica's side (``routers/mturk.py``)."""

from __future__ import annotations

import re
from collections.abc import Mapping
from datetime import timedelta
from typing import TYPE_CHECKING, Any

from sqlalchemy import and_, select
from sqlalchemy.exc import IntegrityError

from server.app.errors import ApiError
from server.app.platforms.base import ID_PATTERN, ArrivalIds, BasePlatform, Handing, Rows
from server.app.platforms.review import (
    AlreadyDone,
    Reviewed,
    ReviewRefused,
    ReviewUnavailable,
)
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import utcnow
from server.app.storage.records import table_of
from server.app.storage.replica_models import ReplicaAssignment, ReplicaBonus, ReplicaSubmission
from server.app.storage.vocabulary import ReplicaAssignmentStatus, ReviewDecision

if TYPE_CHECKING:
    from server.app.study_file import StudyConfig

# The assignmentId of a HIT's preview, before a worker accepts it.
PREVIEW_ASSIGNMENT = "ASSIGNMENT_ID_NOT_AVAILABLE"

# MTurk's answer to a SendBonus whose UniqueRequestToken it has already carried out (the docs:
# "subsequent calls will return an error with a message containing the request ID").
ALREADY_PAID = re.compile(r"already (exists|been (processed|granted|sent))|idempoten", re.I)


# How long MTurk remembers a UniqueRequestToken (its API reference: "The unique token expires
# after 24 hours"): a SendBonus resent after it could pay the bonus again.
MTURK_TOKEN_MEMORY = timedelta(hours=24)
# An assignment's AssignmentStatus that is a decision, as ours (the replica stores ours).
MTURK_DECISIONS = {"Approved": ReviewDecision.APPROVED, "Rejected": ReviewDecision.REJECTED}
DECISIONS = tuple(ReviewDecision)
# A replica assignment whose work was submitted (and perhaps reviewed): a bonus may be paid.
REVIEWABLE = (
    ReplicaAssignmentStatus.SUBMITTED,
    ReplicaAssignmentStatus.APPROVED,
    ReplicaAssignmentStatus.REJECTED,
)


class MTurkReplicaBackend:
    """The replica's side: an assignment is approved or rejected once, after it was submitted,
    and a bonus goes to the worker of a submitted assignment, once per UniqueRequestToken (a
    second call with the token is answered "already exists", as MTurk does)."""

    name = "mturk-replica"
    platform = "mturk"
    currency = "USD"
    repeat_pay_is_safe = True
    token_memory: timedelta | None = MTURK_TOKEN_MEMORY

    def __init__(self, db: Database) -> None:
        self.db = db

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

    def _decide(self, assignment_id: str, status: ReviewDecision, message: str | None) -> None:
        with self.db.write() as s:
            row = self._latest(s, assignment_id)
            if row.status != ReplicaAssignmentStatus.SUBMITTED:
                raise ReviewRefused(
                    f"assignment {assignment_id} is {row.status}: only a submitted assignment "
                    "can be approved or rejected"
                )
            row.status = status
            row.reviewed_at = utcnow()
            row.requester_feedback = message

    def approve(self, who: Reviewed, message: str | None) -> None:
        self._decide(who.platform_submission_id, ReviewDecision.APPROVED, message)

    def reject(self, who: Reviewed, message: str, category: str | None) -> None:
        self._decide(who.platform_submission_id, ReviewDecision.REJECTED, message)

    def decision_of(self, who: Reviewed) -> ReviewDecision | None:
        with self.db.read() as s:
            status = self._latest(s, who.platform_submission_id).status
        return ReviewDecision(status) if status in DECISIONS else None

    def set_up_bonus(self, who: Reviewed, amount: str, reason: str) -> str | None:
        return None

    def bonuses_paid(self, who: Reviewed) -> list[int] | None:
        return None  # a repeat of SendBonus with its token settles an MTurk bonus instead

    def pay_bonus(
        self, who: Reviewed, amount: str, reason: str, token: str, setup_id: str | None
    ) -> None:
        self.send_bonus(
            who.platform_participant_id, who.platform_submission_id, amount, reason, token
        )

    def send_bonus(
        self, worker_id: str, assignment_id: str, amount: str, reason: str, token: str
    ) -> None:
        try:
            with self.db.write() as s:
                row = self._latest(s, assignment_id)
                if row.worker_id != worker_id:
                    raise ReviewRefused(f"assignment {assignment_id} is not worker {worker_id}'s")
                if row.status not in REVIEWABLE:
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
                        unique_request_token=token,
                        granted_at=utcnow(),
                    )
                )
        except IntegrityError:
            raise AlreadyDone(f"the bonus with UniqueRequestToken {token} already exists") from None


class MTurkClientBackend:
    """boto3's MTurk client (or any object with its methods) behind ``ReviewBackend``."""

    name = "mturk"
    platform = "mturk"
    currency = "USD"
    repeat_pay_is_safe = True  # SendBonus's UniqueRequestToken ...
    token_memory: timedelta | None = MTURK_TOKEN_MEMORY  # ... for 24 hours

    def __init__(self, client: Any) -> None:
        self.client = client

    def _call(self, method: str, **arguments: Any) -> Any:
        try:
            return getattr(self.client, method)(**arguments)
        except Exception as error:
            # botocore's ClientError carries MTurk's error code: RequestError is a refusal,
            # ServiceFault (and anything else: no connection, no credentials) a failure.
            response = getattr(error, "response", None)
            details = response.get("Error", {}) if isinstance(response, dict) else {}
            code, message = details.get("Code"), details.get("Message") or str(error)
            if code == "RequestError":
                token = arguments.get("UniqueRequestToken")
                if token is not None and ALREADY_PAID.search(message):
                    raise AlreadyDone(f"MTurk already carried out {token}: {message}") from None
                raise ReviewRefused(f"MTurk refused {method}: {message}") from None
            raise ReviewUnavailable(f"MTurk's {method} failed: {message}") from None

    def approve(self, who: Reviewed, message: str | None) -> None:
        arguments: dict[str, Any] = {"AssignmentId": who.platform_submission_id}
        if message:
            arguments["RequesterFeedback"] = message
        self._call("approve_assignment", **arguments)

    def reject(self, who: Reviewed, message: str, category: str | None) -> None:
        self._call(
            "reject_assignment", AssignmentId=who.platform_submission_id, RequesterFeedback=message
        )

    def decision_of(self, who: Reviewed) -> ReviewDecision | None:
        answer = self._call("get_assignment", AssignmentId=who.platform_submission_id) or {}
        status = answer.get("Assignment", {}).get("AssignmentStatus")
        return MTURK_DECISIONS.get(status)

    def set_up_bonus(self, who: Reviewed, amount: str, reason: str) -> str | None:
        return None

    def bonuses_paid(self, who: Reviewed) -> list[int] | None:
        return None  # a repeat of SendBonus with its token settles an MTurk bonus instead

    def pay_bonus(
        self, who: Reviewed, amount: str, reason: str, token: str, setup_id: str | None
    ) -> None:
        self._call(
            "send_bonus",
            WorkerId=who.platform_participant_id,
            BonusAmount=amount,
            AssignmentId=who.platform_submission_id,
            Reason=reason,
            UniqueRequestToken=token,
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


MTURK_ASSIGNMENTS = table_of(ReplicaAssignment)
MTURK_SUBMISSIONS = table_of(ReplicaSubmission)
MTURK_BONUSES = table_of(ReplicaBonus)


class MTurk(BasePlatform):
    """Workers arrive with assignmentId, hitId, workerId and turkSubmitTo (a preview with
    assignmentId ``ASSIGNMENT_ID_NOT_AVAILABLE``), and submit their code to turkSubmitTo's
    externalSubmit; an assignment returned goes to the next worker who accepts the HIT."""

    name = "mturk"
    display_name = "Mechanical Turk"
    parameters = {
        "assignmentId": ID_PATTERN,
        "hitId": ID_PATTERN,
        "workerId": ID_PATTERN,
        "turkSubmitTo": r"^[\s\S]{0,512}$",
    }
    ids = {
        "platform_participant_id": "workerId",
        "platform_submission_id": "assignmentId",
        "platform_study_id": "hitId",
    }
    exclusive_assignments = True
    reviews = True
    done = (
        "Your data has been deleted. To leave this HIT, press \u201cReturn\u201d on Mechanical "
        "Turk\u2019s page (above this study, or in your list of HITs): returning a HIT does not "
        "count against you."
    )

    def arrival(
        self, params: Mapping[str, str], settings: Settings, own_origin: str | None
    ) -> ArrivalIds | None:
        if params.get("assignmentId") == PREVIEW_ASSIGNMENT:
            return None
        ids = super().arrival(params, settings, own_origin)
        assert ids is not None
        submit_to = check_submit_to(params["turkSubmitTo"], settings, own_origin)
        return ArrivalIds(
            ids.name,
            ids.platform_participant_id,
            ids.platform_submission_id,
            ids.platform_study_id,
            submit_to,
        )

    def handing(self, participant: Any, study: StudyConfig, code: str) -> Handing:
        return Handing(
            submit_url=f"{participant.submit_to}/mturk/externalSubmit",
            submit_fields={
                "assignmentId": str(participant.platform_submission_id),
                "completionCode": code,
            },
        )

    def review_backend(
        self, settings: Settings, db: Database, replica: bool
    ) -> MTurkReplicaBackend | MTurkClientBackend:
        if replica:
            return MTurkReplicaBackend(db)
        return MTurkClientBackend(mturk_client(settings))

    def own_replica_rows(self, participant: Any) -> Rows:
        worker, assignment = participant.platform_participant_id, participant.platform_submission_id
        if not worker or not assignment:
            return []
        turn = and_(
            MTURK_ASSIGNMENTS.c.worker_id == worker,
            MTURK_ASSIGNMENTS.c.assignment_id == assignment,
        )
        bonuses = MTURK_BONUSES.c
        return [
            (
                MTURK_SUBMISSIONS,
                MTURK_SUBMISSIONS.c.assignment_row_id.in_(
                    select(MTURK_ASSIGNMENTS.c.id).where(turn)
                ),
            ),
            (MTURK_BONUSES, and_(bonuses.worker_id == worker, bonuses.assignment_id == assignment)),
            (MTURK_ASSIGNMENTS, turn),
        ]


MTURK = MTurk()


def check_submit_to(value: str, settings: Settings, own_origin: str | None) -> str:
    """The origin the completion form posts to: exactly one of MTurk's (or this server's, for
    the local replica), written as the accepted origin, never as the raw parameter. Matching
    whole origins leaves nothing for browsers and URL parsers to read differently (a
    backslash, user info, a port, a control character, a bracketed host)."""
    allowed = {origin.lower(): origin for origin in settings.submit_origins}
    if own_origin is not None and own_origin.isascii() and own_origin.isprintable():
        allowed[own_origin.lower()] = own_origin
    candidate = value[:-1] if value.endswith("/") else value
    origin = allowed.get(candidate.lower())
    if origin is None:
        raise ApiError(
            400,
            f"turkSubmitTo must be one of {', '.join(sorted(settings.submit_origins))} "
            f"(or this server, for its Mechanical Turk replica), got {value[:100]!a}",
        )
    return origin
