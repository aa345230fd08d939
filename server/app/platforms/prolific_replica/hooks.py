"""Webhooks: the workspace's signing secret, the subscriptions and their deliveries, and the
events the replica sends, signed as Prolific signs them."""

from __future__ import annotations

import json
import secrets
from dataclasses import dataclass
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from server.app.platforms.prolific_replica.base import (
    WORKSPACE_ID,
    Refusal,
    StudyChange,
    _workspace_id,
    new_id,
)
from server.app.platforms.prolific_sync import signature
from server.app.storage.db import Database
from server.app.storage.models import utcnow
from server.app.storage.replica_models import (
    ProlificReplicaHookEvent,
    ProlificReplicaHookSecret,
    ProlificReplicaSubscription,
)

# The webhooks' event types (GET /hooks/event-types/).
EVENT_TYPES = (
    "submission.status.change",
    "study.status.change",
    "study.progress.change",
    "study.has_high_return_rate",
)


def hook_secret(s: Session, make: bool = False) -> str | None:
    """The workspace's signing secret; with ``make``, one is made when it has none (the
    replica signs its webhooks with it, so that they need no setting)."""
    row = s.scalar(
        select(ProlificReplicaHookSecret).where(
            ProlificReplicaHookSecret.workspace_id == WORKSPACE_ID
        )
    )
    if row is None and make:
        row = ProlificReplicaHookSecret(
            id=new_id(),
            workspace_id=WORKSPACE_ID,
            value=secrets.token_urlsafe(32),
            created_at=utcnow(),
        )
        s.add(row)
        s.flush()
    return row.value if row is not None else None


def _secret_view(row: ProlificReplicaHookSecret) -> dict[str, Any]:
    return {"id": row.id, "value": row.value, "workspace_id": row.workspace_id}


def create_secret(s: Session, body: dict[str, Any]) -> tuple[int, Any]:
    """``POST /hooks/secrets/``: a new secret for the workspace, which replaces the old one."""
    workspace = _workspace_id(body.get("workspace_id"))
    for old in s.scalars(
        select(ProlificReplicaHookSecret).where(ProlificReplicaHookSecret.workspace_id == workspace)
    ):
        s.delete(old)
    s.flush()
    row = ProlificReplicaHookSecret(
        id=new_id(), workspace_id=workspace, value=secrets.token_urlsafe(32), created_at=utcnow()
    )
    s.add(row)
    return 201, _secret_view(row)


def list_secrets(s: Session, query: dict[str, str]) -> tuple[int, Any]:
    workspace = _workspace_id(query.get("workspace_id"))
    rows = s.scalars(
        select(ProlificReplicaHookSecret).where(ProlificReplicaHookSecret.workspace_id == workspace)
    ).all()
    return 200, {"results": [_secret_view(row) for row in rows]}


def subscription_view(row: ProlificReplicaSubscription) -> dict[str, Any]:
    return {
        "id": row.id,
        "event_type": row.event_type,
        "target_url": row.target_url,
        "is_enabled": row.is_enabled,
        "workspace_id": row.workspace_id,
    }


def _subscription(s: Session, subscription_id: str) -> ProlificReplicaSubscription:
    row = s.get(ProlificReplicaSubscription, subscription_id)
    if row is None:
        raise Refusal(404, f"Subscription {subscription_id} not found.")
    return row


def create_subscription(
    s: Session, body: dict[str, Any], headers: dict[str, str] | None
) -> tuple[int, Any]:
    """``POST /hooks/subscriptions/``: made disabled, its ``X-Hook-Secret`` in the answer's
    headers; it delivers once confirmed with that secret. The workspace needs a signing secret
    first, as on Prolific."""
    workspace = _workspace_id(body.get("workspace_id"))
    event_type = body.get("event_type")
    if event_type not in EVENT_TYPES:
        raise Refusal(400, f"event_type: one of {', '.join(EVENT_TYPES)}.")
    url = body.get("target_url")
    if not isinstance(url, str) or not url.startswith(("https://", "http://")):
        raise Refusal(400, "target_url: Enter a valid URL.")
    if hook_secret(s) is None:
        raise Refusal(
            400, "Create a secret for your workspace (POST /hooks/secrets/) before subscribing."
        )
    row = ProlificReplicaSubscription(
        id=new_id(),
        workspace_id=workspace,
        event_type=event_type,
        target_url=url,
        confirmation=secrets.token_hex(32),
        is_enabled=False,
        created_at=utcnow(),
    )
    s.add(row)
    if headers is not None:
        headers["X-Hook-Secret"] = row.confirmation
    return 201, {"results": [subscription_view(row)]}


def confirm_subscription(s: Session, subscription_id: str, body: dict[str, Any]) -> tuple[int, Any]:
    """``POST /hooks/subscriptions/{id}/`` ``{secret}``: the ``X-Hook-Secret`` of its creation
    enables it; another secret is refused."""
    row = _subscription(s, subscription_id)
    given = body.get("secret")
    if not isinstance(given, str) or not secrets.compare_digest(
        given.encode(), row.confirmation.encode()
    ):
        raise Refusal(400, "secret: not the X-Hook-Secret this subscription was created with.")
    row.is_enabled = True
    return 200, subscription_view(row)


def list_subscriptions(s: Session, query: dict[str, str]) -> tuple[int, Any]:
    """``GET /hooks/subscriptions/``: the enabled ones (``is_enabled=false``: the others)."""
    enabled = query.get("is_enabled", "true") != "false"
    where: list[Any] = [ProlificReplicaSubscription.is_enabled.is_(enabled)]
    if query.get("workspace_id"):
        where.append(ProlificReplicaSubscription.workspace_id == query["workspace_id"])
    rows = s.scalars(
        select(ProlificReplicaSubscription)
        .where(*where)
        .order_by(ProlificReplicaSubscription.created_at, ProlificReplicaSubscription.id)
    ).all()
    return 200, {"results": [subscription_view(row) for row in rows]}


def event_view(row: ProlificReplicaHookEvent) -> dict[str, Any]:
    return {
        "id": row.id,
        "datetime_created": row.created_at.isoformat(),
        "datetime_updated": row.updated_at.isoformat(),
        "event_type": row.event_type,
        "resource_id": row.resource_id,
        "status": row.status,
        "target_url": row.target_url,
        "payload": row.payload,
    }


def subscription_events(s: Session, subscription_id: str, query: dict[str, str]) -> tuple[int, Any]:
    """``GET /hooks/subscriptions/{id}/events/``: its deliveries, oldest first."""
    _subscription(s, subscription_id)
    try:
        offset, limit = int(query.get("offset", "0")), int(query.get("limit", "100"))
    except ValueError:
        raise Refusal(400, "offset and limit are whole numbers.") from None
    where = [ProlificReplicaHookEvent.subscription_id == subscription_id]
    if query.get("status"):
        where.append(ProlificReplicaHookEvent.status == query["status"])
    if query.get("resource_id"):
        where.append(ProlificReplicaHookEvent.resource_id == query["resource_id"])
    rows = s.scalars(
        select(ProlificReplicaHookEvent)
        .where(*where)
        .order_by(ProlificReplicaHookEvent.created_at, ProlificReplicaHookEvent.id)
        .offset(max(offset, 0))
        .limit(max(min(limit, 1000), 1))
    ).all()
    return 200, {"results": [event_view(row) for row in rows]}


@dataclass(frozen=True)
class Delivery:
    """One webhook to send: where, the body, and the event row that records it (None: the
    replica's own server, with no subscription)."""

    target_url: str
    payload: dict[str, Any]
    event_id: str | None


def deliveries(
    s: Session, event_type: str, resource_id: str, payload: dict[str, Any], own_url: str
) -> list[Delivery]:
    """Where the event goes: each enabled subscription to its type (its delivery recorded,
    PENDING), or, with none at all in the workspace, this server's own webhook, so that a
    rehearsal needs no subscription and no setting."""
    subscribed = s.scalars(
        select(ProlificReplicaSubscription).where(ProlificReplicaSubscription.is_enabled.is_(True))
    ).all()
    if not subscribed:
        return [Delivery(own_url, payload, None)]
    sent = []
    now = utcnow()
    for row in subscribed:
        if row.event_type != event_type:
            continue
        event = ProlificReplicaHookEvent(
            id=new_id(),
            subscription_id=row.id,
            event_type=event_type,
            resource_id=resource_id,
            status="PENDING",
            target_url=row.target_url,
            payload=payload,
            created_at=now,
            updated_at=now,
        )
        s.add(event)
        sent.append(Delivery(row.target_url, payload, event.id))
    return sent


def delivered(db: Database, event_id: str | None, succeeded: bool) -> None:
    """Record how the target answered a delivery (SUCCEEDED: 2xx)."""
    if event_id is None:
        return
    with db.write() as s:
        row = s.get(ProlificReplicaHookEvent, event_id)
        if row is not None:
            row.status = "SUCCEEDED" if succeeded else "FAILED"
            row.updated_at = utcnow()


def submission_payload(submission: dict[str, Any]) -> dict[str, Any]:
    """The body of the replica's ``submission.status.change`` for a submission."""
    return {
        "event_type": "submission.status.change",
        "resource_id": submission["id"],
        "study_id": submission["study_id"],
        "participant_id": submission["participant_id"],
        "status": submission["status"],
    }


def study_payload(change: StudyChange) -> dict[str, Any]:
    """Prolific's ``study.status.change`` body: the study's id as ``resource_id``, its new
    status, ``metadata``."""
    return {
        "resource_id": change.study_id,
        "event_type": "study.status.change",
        "metadata": {},
        "status": change.status,
    }


def status_event(
    secret: str, submission: dict[str, Any], timestamp: int
) -> tuple[dict[str, str], bytes]:
    """The replica's ``submission.status.change`` webhook for a submission, signed as Prolific
    signs it: the headers and the body."""
    body = json.dumps(submission_payload(submission)).encode()
    # When the status changed: the replica sends at once.
    return signed(secret, body, timestamp, str(timestamp)), body


def study_status_event(
    secret: str, change: StudyChange, timestamp: int
) -> tuple[dict[str, str], bytes]:
    """The replica's ``study.status.change`` webhook, signed as its submission events are; its
    ``X-Timestamp`` is the change's own time, to the microsecond, so that two changes in one
    second keep their order."""
    body = json.dumps(study_payload(change)).encode()
    return signed(secret, body, timestamp, change.at.isoformat()), body


def signed(secret: str, body: bytes, timestamp: int, event_time: str) -> dict[str, str]:
    """A webhook's headers, as Prolific signs its deliveries: the signature of the timestamp
    and the body, a new event id, and ``X-Timestamp`` (``event_time``: when it happened)."""
    stamp = str(timestamp)
    return {
        "Content-Type": "application/json",
        "X-Prolific-Request-Signature": signature(secret, stamp, body),
        "X-Prolific-Request-Timestamp": stamp,
        "X-Event-ID": secrets.token_hex(16),
        "X-Timestamp": event_time,
    }
