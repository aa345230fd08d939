"""Messages to participants who took part in a study: sent, kept for 30 days, and listed."""

from __future__ import annotations

import hashlib
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from server.app.platforms.prolific_replica.base import Refusal, _study, new_id
from server.app.storage.models import utcnow
from server.app.storage.replica_models import (
    ProlificReplicaMessage,
    ProlificReplicaSubmission,
)

# The replica's one researcher, the sender of every message.
RESEARCHER_ID = "5e0f000000000000000000c1"
# GET /messages/ lists "up to the last 30 days of messages".
MESSAGES_KEPT = timedelta(days=30)


def _message_text(body: dict[str, Any]) -> str:
    text = body.get("body")
    if not isinstance(text, str) or not text.strip():
        raise Refusal(400, "body: This field may not be blank.")
    return text


def _recipients(s: Session, study_id: Any, ids: list[Any]) -> list[str]:
    """The recipients, each a participant with a submission in the study (Prolific lets a
    researcher message only those who took part in their studies), or a refusal naming the
    first who is not."""
    if not isinstance(study_id, str) or not study_id:
        raise Refusal(400, "study_id: This field is required.")
    _study(s, study_id)
    if not ids or not all(isinstance(i, str) and i for i in ids):
        raise Refusal(400, "recipient ids: a participant id is required.")
    taken = set(
        s.scalars(
            select(ProlificReplicaSubmission.participant_id).where(
                ProlificReplicaSubmission.study_id == study_id,
                ProlificReplicaSubmission.participant_id.in_(ids),
            )
        )
    )
    for who in ids:
        if who not in taken:
            raise Refusal(
                400,
                f"Participant {who} has no submission in study {study_id}: you can message "
                "only participants who took part in your studies.",
            )
    return list(dict.fromkeys(ids))


def _send(s: Session, study_id: str, recipients: list[str], text: str) -> tuple[int, Any]:
    now = utcnow()
    for who in recipients:
        s.add(
            ProlificReplicaMessage(
                id=new_id(),
                sender_id=RESEARCHER_ID,
                recipient_id=who,
                study_id=study_id,
                body=text,
                sent_at=now,
            )
        )
    return 204, None


def send_message(s: Session, body: dict[str, Any]) -> tuple[int, Any]:
    """``POST /messages/`` ``{recipient_id, body, study_id}``: 204, the message sent."""
    text = _message_text(body)
    recipients = _recipients(s, body.get("study_id"), [body.get("recipient_id")])
    return _send(s, body["study_id"], recipients, text)


def bulk_message(s: Session, body: dict[str, Any]) -> tuple[int, Any]:
    """``POST /messages/bulk/`` ``{ids, body, study_id}``: 204, sent to every one of them, or
    refused (400) and sent to none."""
    text = _message_text(body)
    ids = body.get("ids")
    if not isinstance(ids, list):
        raise Refusal(400, "ids: a list of participant ids is required.")
    recipients = _recipients(s, body.get("study_id"), ids)
    return _send(s, body["study_id"], recipients, text)


def message_view(row: ProlificReplicaMessage) -> dict[str, Any]:
    channel = hashlib.sha256(f"{row.sender_id}:{row.recipient_id}".encode()).hexdigest()[:24]
    return {
        "id": row.id,
        "sender_id": row.sender_id,
        "body": row.body,
        "sent_at": row.sent_at.isoformat(),
        "type": "message",
        "channel_id": channel,
        "data": {"study_id": row.study_id},
    }


def list_messages(s: Session, query: dict[str, str]) -> tuple[int, Any]:
    """``GET /messages/?user_id=`` (the messages with that participant) or ``?created_after=``
    (all messages since then), of the last 30 days, oldest first."""
    since = utcnow() - MESSAGES_KEPT
    where = [ProlificReplicaMessage.sent_at >= since]
    if query.get("user_id"):
        where.append(ProlificReplicaMessage.recipient_id == query["user_id"])
    elif query.get("created_after"):
        try:
            after = datetime.fromisoformat(query["created_after"].replace("Z", "+00:00"))
        except ValueError:
            raise Refusal(400, "created_after: a date and time in ISO 8601.") from None
        if after.tzinfo is None:
            after = after.replace(tzinfo=since.tzinfo)
        where.append(ProlificReplicaMessage.sent_at > after)
    else:
        raise Refusal(400, "user_id or created_after is required.")
    rows = s.scalars(
        select(ProlificReplicaMessage)
        .where(*where)
        .order_by(ProlificReplicaMessage.sent_at, ProlificReplicaMessage.id)
    ).all()
    return 200, {"results": [message_view(row) for row in rows]}
