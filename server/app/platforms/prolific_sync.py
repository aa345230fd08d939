"""Prolific's submission statuses kept in step with the study: from Prolific's webhook
(``submission.status.change``, signature checked, each event applied once) and from a poll of
the study's submissions (for a server without a public https address).

A participant still working whose submission is RETURNED or TIMED-OUT is released at once
(one who had finished keeps their status, see ``NOT_RELEASED``): their flow status becomes
``returned`` (so they no longer count in the balanced domain assignment, and the
study's pages refuse to go on), their active learning sessions stop, and their data stays,
marked with Prolific's status.

A submission completed with a code that asks for a return (our NO_CONSENT code, with Prolific's
REQUEST_RETURN action) is AWAITING REVIEW with ``return_requested`` set: the participant is asked
to return it, and Prolific approves it by itself 21 days after its completion if they never do.
Both times are kept (``platform_completed_at``, ``platform_return_requested_at``): from
Prolific's record of the submission in a poll, and, from the webhook (whose body has the status
only), from the event's time.

The study's own events are kept per study (``ProlificStudy``): ``study.status.change`` its
Prolific status and when it took it (ordered by the event's time, as a submission's status),
``study.has_high_return_rate`` Prolific's warning, which the dashboard shows beside our own
count of the study's returns (``returns_of``)."""

from __future__ import annotations

import base64
import hashlib
import hmac
import time
from collections.abc import Callable, Mapping
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from server.app.platforms.prolific import STUDY_STATUSES, SUBMISSION_STATUSES, ProlificClient
from server.app.storage.db import Database
from server.app.storage.models import (
    LearningSession,
    Participant,
    ProlificEvent,
    ProlificStudy,
    ProlificWebhookSecret,
    StatusChange,
    utcnow,
)
from server.app.storage.replica_models import ProlificReplicaHookSecret
from server.app.storage.vocabulary import ParticipantStatus, SessionStatus

RELEASED = ("RETURNED", "TIMED-OUT")
# Flow statuses a RETURNED or TIMED-OUT submission leaves as they are: the flow had ended, or
# the participant had finished, which Prolific allows past the time limit ("Participants can
# still complete their submission if they go over the time limit"); such a finisher stays
# reviewable, marked with Prolific's status.
NOT_RELEASED = (
    ParticipantStatus.RETURNED,
    ParticipantStatus.DECLINED,
    ParticipantStatus.COMPLETED,
    ParticipantStatus.SUBMITTED,
)
# A webhook older (or newer) than this is refused: a replay of a captured request.
WEBHOOK_MAX_AGE_SECONDS = 300


class WebhookRefused(Exception):
    """Not a genuine, fresh Prolific webhook."""


def signature(secret: str, timestamp: str, body: bytes) -> str:
    """Prolific's X-Prolific-Request-Signature: base64(HMAC-SHA256(secret, timestamp + body))."""
    digest = hmac.new(secret.encode(), timestamp.encode() + body, hashlib.sha256).digest()
    return base64.b64encode(digest).decode()


def verify(
    secret: str, timestamp: str | None, given: str | None, body: bytes, now: float | None = None
) -> None:
    if not timestamp or not given:
        raise WebhookRefused("the request is not signed")
    # ASCII digits only (``"²³".isdigit()`` holds), and few enough to be a time: a longer one
    # overflows the subtraction below.
    if not (timestamp.isascii() and timestamp.isdigit() and len(timestamp) <= 12):
        raise WebhookRefused("the timestamp is not a UNIX time")
    age = (time.time() if now is None else now) - int(timestamp)
    if abs(age) > WEBHOOK_MAX_AGE_SECONDS:
        raise WebhookRefused(f"the request is {int(age)} s old: a replay is refused")
    if not hmac.compare_digest(signature(secret, timestamp, body).encode(), given.encode()):
        raise WebhookRefused("the signature does not match")


def verify_any(
    known: list[str],
    timestamp: str | None,
    given: str | None,
    body: bytes,
    now: float | None = None,
) -> None:
    """``verify`` against each secret the server knows: signed with any one of them passes."""
    refused = WebhookRefused("no webhook secret")
    for secret in known:
        try:
            verify(secret, timestamp, given, body, now)
        except WebhookRefused as error:
            refused = error
        else:
            return
    raise refused


def webhook_secrets(db: Database, settings: Any) -> list[str]:
    """The secrets a webhook may be signed with: ``BAM_PROLIFIC_WEBHOOK_SECRET``, each
    workspace's secret that ``bam-study prolific hooks`` stored, and this server's Prolific
    replica's own workspace secret (its events need no setting)."""
    known = []
    if settings.prolific_webhook_secret is not None:
        known.append(settings.prolific_webhook_secret.get_secret_value())
    with db.read() as s:
        known += list(s.scalars(select(ProlificWebhookSecret.secret)))
        known += list(s.scalars(select(ProlificReplicaHookSecret.value)))
    return known


# Statuses Prolific reports that say nothing lasting: ``PROCESSING`` between an approval or a
# rejection and its result, ``UNKNOWN``; answered and left out, the status stays as it was.
TRANSIENT_STATUSES = ("PROCESSING", "UNKNOWN")


def apply_status(
    db: Database,
    study_id: str | None,
    submission_id: str,
    status: str,
    at: datetime | None = None,
    record: Mapping[str, Any] | None = None,
) -> bool:
    """Store Prolific's status of the submission, true at ``at`` (now: a poll's reading), and
    release a returned or timed-out participant still in the study; False when no participant
    of ours has that submission. ``record``: Prolific's submission as a poll lists it (its
    ``completed_at`` and ``return_requested`` are kept)."""
    # A poll's reading counts from its whole second: an event stamped in that second (a
    # webhook's time may be in whole seconds) may be the one it read, and applies.
    at = at or utcnow().replace(microsecond=0)
    with db.write() as s:
        return _apply_status(s, study_id, submission_id, status, at, record) != UNKNOWN


APPLIED, OLDER, UNKNOWN = "applied", "older than the status stored", "not a participant"


def _apply_status(
    s: Session,
    study_id: str | None,
    submission_id: str,
    status: str,
    at: datetime,
    record: Mapping[str, Any] | None = None,
) -> str:
    """APPLIED, OLDER (a status true before the one stored: events arrive out of order, and a
    poll reads the status of its moment) or UNKNOWN; ValueError for a status Prolific does not
    have."""
    if status not in SUBMISSION_STATUSES:
        raise ValueError(f"unknown Prolific submission status {status!r}")
    query = select(Participant).where(
        Participant.platform == "prolific", Participant.platform_submission_id == submission_id
    )
    if study_id:
        query = query.where(Participant.platform_study_id == study_id)
    p = s.scalar(query.with_for_update())
    if p is None:
        return UNKNOWN
    if p.platform_status_at is not None and at < p.platform_status_at:
        return OLDER
    p.platform_status, p.platform_status_at = status, at
    _keep_times(p, status, at, record)
    if status in RELEASED and p.status not in NOT_RELEASED:
        now = utcnow()
        p.status = ParticipantStatus.RETURNED
        s.add(
            StatusChange(
                participant_id=p.id,
                status=ParticipantStatus.RETURNED,
                at=now,
                note=f"Prolific: submission {status}; the place went back to Prolific",
            )
        )
        for session in s.scalars(
            select(LearningSession).where(
                LearningSession.participant_id == p.id,
                LearningSession.status == SessionStatus.ACTIVE,
            )
        ):
            session.status = SessionStatus.FINISHED
            session.finished_at = now
    return APPLIED


def _keep_times(
    p: Participant, status: str, at: datetime, record: Mapping[str, Any] | None
) -> None:
    """When Prolific completed the submission and asked for its return: Prolific's own record
    where a poll read it; else, for a status from the webhook, the event's time."""
    recorded = record is not None and "return_requested" in record
    if record is not None:
        completed = event_time(str(record.get("completed_at") or ""))
        if completed is not None:
            p.platform_completed_at = completed
        if recorded:  # Prolific's word, a null one included
            p.platform_return_requested_at = event_time(str(record["return_requested"] or ""))
    if status != "AWAITING REVIEW":
        return
    if p.platform_completed_at is None:
        p.platform_completed_at = at
    # Our page sends a participant who declined with the study's NO_CONSENT code, which asks for
    # a return (REQUEST_RETURN, ``prolific.draft_study``): their submission completed, Prolific
    # has asked them to return it. A poll replaces this with Prolific's own record.
    if not recorded and p.status == "declined" and p.platform_return_requested_at is None:
        p.platform_return_requested_at = at


def reconcile_submissions(db: Database, client: ProlificClient, study_id: str) -> dict[str, str]:
    """Poll the study's submissions (page by page) and apply every status; the statuses of
    our participants' submissions."""
    seen: dict[str, str] = {}
    for submission in client.submissions(study_id):
        status = str(submission.get("status"))
        if status in SUBMISSION_STATUSES and apply_status(
            db, study_id, submission["id"], status, record=submission
        ):
            seen[submission["id"]] = status
    return seen


def event_time(header: str | None) -> datetime | None:
    """When the event happened, from Prolific's ``X-Timestamp`` (UNIX seconds or ISO 8601);
    None without one, or one that is not a time."""
    if not header or len(header) > 40:
        return None
    text = header.strip()
    digits = text.replace(".", "", 1)
    try:
        if digits.isascii() and digits.isdigit():
            return datetime.fromtimestamp(float(text), UTC)
        moment = datetime.fromisoformat(text.replace("Z", "+00:00"))
    except (ValueError, OverflowError, OSError):
        return None
    return moment.replace(tzinfo=UTC) if moment.tzinfo is None else moment.astimezone(UTC)


# The events the webhook applies; Prolific's other one, ``study.progress.change`` (a body with
# the study's id only), is answered and ignored: the poll and the submission events say more.
SUBMISSION_EVENT = "submission.status.change"
STUDY_STATUS_EVENT = "study.status.change"
HIGH_RETURN_RATE_EVENT = "study.has_high_return_rate"
APPLIED_EVENTS = (SUBMISSION_EVENT, STUDY_STATUS_EVENT, HIGH_RETURN_RATE_EVENT)


def apply_webhook(
    db: Database, event_id: str, payload: dict[str, Any], happened_at: datetime | None = None
) -> str:
    """Apply one event (``APPLIED_EVENTS``) once; what was done. The event's id and its effect
    are committed in one transaction: a failure between the two leaves neither, so Prolific's
    redelivery applies it (an id committed alone would answer "already applied" and lose the
    change). ``happened_at`` (``event_time``) orders the events: one older than the status
    stored leaves it; without it the event counts as happening on arrival. ValueError for a
    status Prolific does not have (nothing is written)."""
    event_type = str(payload.get("event_type", ""))
    if event_type not in APPLIED_EVENTS:
        return f"event {event_type!r} ignored"
    resource_id = payload.get("resource_id")
    if not isinstance(resource_id, str) or not resource_id:
        return "no resource_id"
    at = happened_at or utcnow()
    if event_type == HIGH_RETURN_RATE_EVENT:
        metadata = payload.get("metadata")
        return _once(
            db,
            event_id,
            event_type,
            lambda s: _warn_high_return_rate(
                s, resource_id, at, metadata if isinstance(metadata, dict) else {}
            ),
        )
    status = payload.get("status")
    if not isinstance(status, str):
        return "no status"
    if event_type == STUDY_STATUS_EVENT:
        if status not in STUDY_STATUSES:
            raise ValueError(f"unknown Prolific study status {status!r}")
        return _once(
            db, event_id, event_type, lambda s: _apply_study_status(s, resource_id, status, at)
        )
    if status in TRANSIENT_STATUSES:
        return f"status {status} is transient: the submission's status is kept"
    study_id = payload.get("study_id")
    return _once(
        db,
        event_id,
        event_type,
        lambda s: _apply_status(
            s, study_id if isinstance(study_id, str) else None, resource_id, status, at
        ),
    )


def _once(db: Database, event_id: str, event_type: str, apply: Callable[[Session], str]) -> str:
    """Record the event's id and apply it in one transaction; "already applied" for an id seen."""
    try:
        with db.write() as s:
            s.add(ProlificEvent(event_id=event_id, event_type=event_type, received_at=utcnow()))
            s.flush()  # a redelivered id fails here, before anything else is written
            outcome = apply(s)
    except IntegrityError:
        return "already applied"
    if outcome == UNKNOWN:
        return "not a participant of this study"
    return "applied" if outcome == APPLIED else f"not applied: {OLDER}"


def _study(s: Session, study_id: str) -> ProlificStudy:
    """The study's row, locked (made on its first event)."""
    row = s.get(ProlificStudy, study_id, with_for_update=True)
    if row is not None:
        return row
    try:
        with s.begin_nested():  # two first events at once: the second's insert fails here
            row = ProlificStudy(study_id=study_id)
            s.add(row)
    except IntegrityError:
        row = s.get(ProlificStudy, study_id, with_for_update=True, populate_existing=True)
        assert row is not None
    return row


def _apply_study_status(s: Session, study_id: str, status: str, at: datetime) -> str:
    row = _study(s, study_id)
    if row.status_at is not None and at < row.status_at:
        return OLDER
    row.status, row.status_at = status, at
    return APPLIED


def record_study_status(db: Database, study_id: str, status: str, at: datetime) -> None:
    """Keep Prolific's answer to a change the server sent (its status then), as its event
    would (an event stamped later still wins)."""
    with db.write() as s:
        _apply_study_status(s, study_id, status, at)


def _warn_high_return_rate(
    s: Session, study_id: str, at: datetime, metadata: dict[str, Any]
) -> str:
    row = _study(s, study_id)
    if row.high_return_rate_at is not None and at < row.high_return_rate_at:
        return OLDER
    row.high_return_rate_at, row.high_return_rate_metadata = at, metadata
    return APPLIED


def returns_of(s: Session, study_id: str) -> dict[str, int]:
    """Our own count of the study's returns: ``arrived`` (our participants of the study),
    ``returned`` (their submission RETURNED or TIMED-OUT, or released by the study) and why:
    ``returned on Prolific``, ``timed out``, ``had declined consent`` (among the returned)."""
    rows = s.execute(
        select(Participant.status, Participant.platform_status).where(
            Participant.platform == "prolific", Participant.platform_study_id == study_id
        )
    ).all()
    returned = [
        (status, prolific)
        for status, prolific in rows
        if prolific in RELEASED or status == ParticipantStatus.RETURNED
    ]
    return {
        "arrived": len(rows),
        "returned": len(returned),
        "returned on Prolific": sum(prolific == "RETURNED" for _, prolific in returned),
        "timed out": sum(prolific == "TIMED-OUT" for _, prolific in returned),
        "had declined consent": sum(status == ParticipantStatus.DECLINED for status, _ in returned),
    }
