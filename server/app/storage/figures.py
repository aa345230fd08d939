"""Figures about a participant that the dashboard and the export both show, computed once."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from datetime import datetime

from server.app.storage.models import LearningSession, Participant
from server.app.storage.vocabulary import SessionKind


@dataclass(frozen=True)
class ParticipantFigures:
    minutes: float  # from arrival to completion (or to the last request, if not completed)
    agents: int  # study sessions (not tutorials)
    agents_finished: int


def study_sessions_by_participant(
    sessions: Iterable[LearningSession],
) -> dict[int, list[LearningSession]]:
    """Each participant's study sessions (tutorials left out), in one pass over the sessions."""
    grouped: dict[int, list[LearningSession]] = {}
    for session in sessions:
        if session.kind == SessionKind.STUDY:
            grouped.setdefault(session.participant_id, []).append(session)
    return grouped


def participant_figures(
    participant: Participant,
    study_sessions: list[LearningSession],
    completed_at: datetime | None,
) -> ParticipantFigures:
    end = completed_at or participant.last_seen_at
    return ParticipantFigures(
        minutes=round((end - participant.created_at).total_seconds() / 60, 2),
        agents=len(study_sessions),
        agents_finished=sum(1 for x in study_sessions if x.completed),
    )
