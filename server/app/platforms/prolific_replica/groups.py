"""Participant groups: made, listed, joined and left, by the API or by a completion code's
actions; and the study filters that keep out whom they name."""

from __future__ import annotations

import re
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from server.app.platforms.prolific_replica.base import Refusal, _workspace_id, new_id
from server.app.storage.models import utcnow
from server.app.storage.replica_models import (
    ProlificReplicaGroupMember,
    ProlificReplicaParticipantGroup,
    ProlificReplicaStudy,
    ProlificReplicaSubmission,
)


def _group(s: Session, group_id: str) -> ProlificReplicaParticipantGroup:
    row = s.get(ProlificReplicaParticipantGroup, group_id)
    if row is None or row.is_deleted:
        raise Refusal(404, f"Participant group {group_id} not found.")
    return row


def _members(s: Session, group_id: str) -> list[ProlificReplicaGroupMember]:
    return list(
        s.scalars(
            select(ProlificReplicaGroupMember)
            .where(ProlificReplicaGroupMember.group_id == group_id)
            .order_by(
                ProlificReplicaGroupMember.created_at, ProlificReplicaGroupMember.participant_id
            )
        )
    )


def group_view(s: Session, row: ProlificReplicaParticipantGroup) -> dict[str, Any]:
    feeders = [
        {"id": study.id, "name": study.name}
        for study in s.scalars(select(ProlificReplicaStudy).order_by(ProlificReplicaStudy.id))
        if row.id in _code_groups(study.fields)
    ]
    return {
        "id": row.id,
        "name": row.name,
        "project_id": None,
        "workspace_id": row.workspace_id,
        "organisation_id": None,
        "description": row.description,
        "participant_count": len(_members(s, row.id)),
        "is_deleted": row.is_deleted,
        "feeder_studies": feeders,
    }


def _code_groups(fields: dict[str, Any]) -> set[str]:
    """The groups the study's completion codes add to or remove from."""
    return {
        str(action.get("participant_group"))
        for code in fields.get("completion_codes") or []
        for action in code.get("actions") or []
        if isinstance(action, dict)
        and action.get("action") in ("ADD_TO_PARTICIPANT_GROUP", "REMOVE_FROM_PARTICIPANT_GROUP")
    }


def _participant_ids(body: dict[str, Any], name: str = "participant_ids") -> list[str]:
    ids = body.get(name, [])
    if not isinstance(ids, list) or not all(
        isinstance(i, str) and re.fullmatch(r"[0-9a-f]{24}", i) for i in ids
    ):
        raise Refusal(400, f"{name}: a list of participant ids.")
    return list(dict.fromkeys(ids))


def add_members(s: Session, group_id: str, participant_ids: list[str]) -> None:
    """Add participants who are not members yet (members already in are ignored)."""
    have = {m.participant_id for m in _members(s, group_id)}
    now = utcnow()
    for who in participant_ids:
        if who not in have:
            s.add(ProlificReplicaGroupMember(group_id=group_id, participant_id=who, created_at=now))
    s.flush()


def remove_members(s: Session, group_id: str, participant_ids: list[str]) -> None:
    for member in _members(s, group_id):
        if member.participant_id in participant_ids:
            s.delete(member)
    s.flush()


def create_group(s: Session, body: dict[str, Any]) -> tuple[int, Any]:
    """``POST /participant-groups/`` ``{workspace_id, name, description, participant_ids}``."""
    workspace = _workspace_id(body.get("workspace_id"))
    name = body.get("name")
    if not isinstance(name, str) or not name.strip():
        raise Refusal(400, "name: This field is required.")
    description = body.get("description")
    row = ProlificReplicaParticipantGroup(
        id=new_id(),
        workspace_id=workspace,
        name=name,
        description=description if isinstance(description, str) else None,
        is_deleted=False,
        created_at=utcnow(),
    )
    s.add(row)
    s.flush()
    add_members(s, row.id, _participant_ids(body))
    return 201, group_view(s, row)


def list_groups(s: Session, query: dict[str, str]) -> tuple[int, Any]:
    """``GET /participant-groups/?workspace_id=``: the workspace's groups not deleted."""
    workspace = _workspace_id(query.get("workspace_id"))
    rows = s.scalars(
        select(ProlificReplicaParticipantGroup)
        .where(
            ProlificReplicaParticipantGroup.workspace_id == workspace,
            ProlificReplicaParticipantGroup.is_deleted.is_(False),
        )
        .order_by(ProlificReplicaParticipantGroup.created_at, ProlificReplicaParticipantGroup.id)
    ).all()
    return 200, {"results": [group_view(s, row) for row in rows]}


def membership_view(s: Session, group_id: str) -> dict[str, Any]:
    return {
        "results": [
            {"participant_id": m.participant_id, "datetime_created": m.created_at.isoformat()}
            for m in _members(s, group_id)
        ]
    }


def group_members(s: Session, method: str, group_id: str, body: dict[str, Any]) -> tuple[int, Any]:
    """``GET``, ``POST`` (add) and ``DELETE`` (remove) ``/participant-groups/{id}/participants/``:
    the group's members after the change."""
    _group(s, group_id)
    if method == "POST":
        add_members(s, group_id, _participant_ids(body))
    elif method == "DELETE":
        remove_members(s, group_id, _participant_ids(body))
    return 200, membership_view(s, group_id)


def in_group(s: Session, group_ids: list[str], participant_id: str) -> bool:
    found = s.scalar(
        select(ProlificReplicaGroupMember.group_id).where(
            ProlificReplicaGroupMember.group_id.in_(group_ids),
            ProlificReplicaGroupMember.participant_id == participant_id,
        )
    )
    return found is not None


def barred(s: Session, study: ProlificReplicaStudy, participant_id: str) -> str | None:
    """Why the study keeps the participant out (None: they may take part): a submission of it
    already, a study of ``previous_studies_blocklist`` taken, a group of ``participant_group_blocklist`` joined, or
    no group of ``participant_group_allowlist``."""
    again = s.scalar(
        select(ProlificReplicaSubmission.id).where(
            ProlificReplicaSubmission.study_id == study.id,
            ProlificReplicaSubmission.participant_id == participant_id,
        )
    )
    if again is not None:
        return "they took part in it already (one submission per participant)"
    for item in study.fields.get("filters") or []:
        values = list(item.get("selected_values") or [])
        kind = item.get("filter_id")
        if kind == "previous_studies_blocklist":
            taken = s.scalar(
                select(ProlificReplicaSubmission.id).where(
                    ProlificReplicaSubmission.study_id.in_(values),
                    ProlificReplicaSubmission.participant_id == participant_id,
                )
            )
            if taken is not None:
                return "they took part in a study of its previous_studies_blocklist"
        if kind == "participant_group_blocklist" and in_group(s, values, participant_id):
            return "they are in a participant group of its participant_group_blocklist"
        if kind == "participant_group_allowlist" and not in_group(s, values, participant_id):
            return "they are in no participant group of its participant_group_allowlist"
    return None


def code_actions(s: Session, code: dict[str, Any], participant_id: str) -> None:
    """A completion code's group actions, carried out for the participant who gave it."""
    for action in code.get("actions") or []:
        if not isinstance(action, dict):
            continue
        group = action.get("participant_group")
        if action.get("action") == "ADD_TO_PARTICIPANT_GROUP" and isinstance(group, str):
            if s.get(ProlificReplicaParticipantGroup, group) is not None:
                add_members(s, group, [participant_id])
        if action.get("action") == "REMOVE_FROM_PARTICIPANT_GROUP" and isinstance(group, str):
            remove_members(s, group, [participant_id])
