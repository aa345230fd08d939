"""What the participant's page is shown: the participant's state, progress and sessions."""

from __future__ import annotations

from typing import Any

from sqlalchemy import Connection, select

from server.app.participants.completion import completion
from server.app.schemas import (
    AttentionCheckView,
    ParticipantBrief,
    ParticipantState,
    Progress,
    SessionSummary,
)
from server.app.storage.records import load_all
from server.app.storage.tables import CHECKS, SESSIONS
from server.app.storage.vocabulary import CheckStatus, SessionKind, SessionStatus
from server.app.study_file import StudyConfig


def current_session_id(c: Connection, participant: Any) -> int | None:
    return c.scalar(
        select(SESSIONS.c.id).where(
            SESSIONS.c.participant_id == participant.id, SESSIONS.c.status == SessionStatus.ACTIVE
        )
    )


def brief(participant: Any, study: StudyConfig, session_id: int | None) -> ParticipantBrief:
    return ParticipantBrief(
        status=participant.status,
        current_session_id=session_id,
        next_seq=participant.next_seq,
        completion=completion(participant, study),
    )


def summary(session: Any) -> SessionSummary:
    return SessionSummary(
        session_id=session.id,
        kind=session.kind,
        position=session.position,
        domain=session.domain,
        environment=session.environment,
        colour={"name": session.colour_name, "hex": session.colour_hex},  # type: ignore[arg-type]
        status=session.status,
        opened=session.opened_at is not None,
    )


def participant_state(c: Connection, participant: Any, study: StudyConfig) -> ParticipantState:
    sessions = load_all(
        c, SESSIONS, SESSIONS.c.participant_id == participant.id, order_by=SESSIONS.c.ordinal
    )
    study_sessions = [x for x in sessions if x.kind == SessionKind.STUDY]
    reached = [x for x in study_sessions if x.status != SessionStatus.PENDING]
    current = next((x.id for x in sessions if x.status == SessionStatus.ACTIVE), None)
    return ParticipantState(
        participant_id=participant.id,
        platform=participant.platform,
        status=participant.status,
        domain=participant.domain,
        current_session_id=current,
        next_seq=participant.next_seq,
        completion=completion(participant, study),
        progress=Progress(agent=len(reached), of=len(study_sessions)),
        sessions=[summary(x) for x in sessions],
        tutorial_step=participant.tutorial_step,
        attention_check=attention_check(c, participant),
    )


def attention_check(c: Connection, participant: Any) -> AttentionCheckView | None:
    """The attention check being taken (``participants.attention``), if any."""
    checks = load_all(c, CHECKS, CHECKS.c.participant_id == participant.id)
    active = next((x for x in checks if x.status == CheckStatus.ACTIVE), None)
    return None if active is None else check_view(active, len(checks))


def check_view(check: Any, of: int) -> AttentionCheckView:
    """An attention check as the page draws it (``of``: the participant's checks)."""
    return AttentionCheckView(
        number=check.number + 1,
        of=of,
        size=check.size,
        robot=divmod(check.cell, check.size),
        star=divmod(check.star_cell, check.size),
        moves_made=len(check.moves),
        moves_allowed=check.moves_allowed,
        status=check.status,
    )
