"""What the export reads: every table's rows in one read transaction (``read_study``), and the
figures the rows are written with (``Context``: first times per status, per-session counts,
pseudonyms).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

from sqlalchemy import select

from server.app.rights.pseudonyms import pseudonym
from server.app.storage.db import Database
from server.app.storage.figures import (
    ParticipantFigures,
    participant_figures,
    study_sessions_by_participant,
)
from server.app.storage.models import (
    AttentionCheck,
    Bonus,
    Episode,
    Erasure,
    Event,
    LearnerUpdate,
    LearningSession,
    Message,
    Participant,
    QuestionnaireAnswer,
    Review,
    StatusChange,
)
from server.app.storage.vocabulary import EpisodeKind, Observed, ParticipantStatus, UpdateStatus


@dataclass(frozen=True)
class Study:
    """Every row the export writes from, in the files' order."""

    participants: Sequence[Participant]
    changes: Sequence[StatusChange]
    answers: Sequence[QuestionnaireAnswer]
    reviews: Sequence[Review]
    bonuses: Sequence[Bonus]
    messages: Sequence[Message]
    erasures: Sequence[Erasure]
    checks: Sequence[AttentionCheck]
    sessions: Sequence[LearningSession]
    episodes: Sequence[Episode]
    updates: Sequence[Any]  # rows of LearnerUpdate's columns below (no learner state)
    events: Sequence[Any]  # rows of Event's columns below


_UPDATE_COLUMNS = (
    LearnerUpdate.session_id,
    LearnerUpdate.update_index,
    LearnerUpdate.status,
    LearnerUpdate.episodes,
    LearnerUpdate.actions,
    LearnerUpdate.normalized_return,
    LearnerUpdate.objective,
    LearnerUpdate.seconds,
    LearnerUpdate.queued_at,
    LearnerUpdate.finished_at,
)
_EVENT_COLUMNS = (
    Event.id,
    Event.participant_id,
    Event.session_id,
    Event.seq,
    Event.kind,
    Event.created_at,
    Event.task,
    Event.mode,
    Event.state,
    Event.action,
    Event.next_state,
    Event.feedback,
    Event.episode_index,
    Event.record,
    Event.stay_state,
    Event.episode_end,
)


def read_study(db: Database) -> Study:
    """Every row the export needs, in one read transaction."""
    with db.read() as s:
        return Study(
            participants=s.scalars(select(Participant).order_by(Participant.id)).all(),
            changes=s.scalars(select(StatusChange).order_by(StatusChange.id)).all(),
            answers=s.scalars(select(QuestionnaireAnswer).order_by(QuestionnaireAnswer.id)).all(),
            reviews=s.scalars(select(Review).order_by(Review.id)).all(),
            bonuses=s.scalars(select(Bonus).order_by(Bonus.id)).all(),
            messages=s.scalars(select(Message).order_by(Message.id)).all(),
            erasures=s.scalars(select(Erasure).order_by(Erasure.id)).all(),
            checks=s.scalars(
                select(AttentionCheck).order_by(
                    AttentionCheck.participant_id, AttentionCheck.number
                )
            ).all(),
            sessions=s.scalars(select(LearningSession).order_by(LearningSession.id)).all(),
            episodes=s.scalars(select(Episode).order_by(Episode.id)).all(),
            updates=s.execute(
                select(*_UPDATE_COLUMNS)
                .where(LearnerUpdate.status != UpdateStatus.PENDING)
                .order_by(LearnerUpdate.session_id, LearnerUpdate.update_index)
            ).all(),
            events=s.execute(select(*_EVENT_COLUMNS).order_by(Event.id)).all(),
        )


@dataclass
class SessionCounts:
    """A learning session's figures counted from its events, episodes and updates."""

    demonstrated_actions: int = 0
    agent_actions: int = 0
    feedback_given: int = 0
    demonstrations: int = 0  # episodes ended
    agent_episodes: int = 0
    updates: int = 0  # processed, update 0 (the untrained learner's evaluation) left out
    final_normalized_return: float | None = None


_NO_COUNTS = SessionCounts()


@dataclass
class Context:
    """What the rows are written with besides their own fields."""

    study: Study
    pseudonymize: bool
    secret: str | None
    first_at: dict[int, dict[str, datetime]] = field(default_factory=dict)
    scrubbed: set[int] = field(default_factory=set)
    session_by_id: dict[int, LearningSession] = field(default_factory=dict)
    position_of: dict[tuple[int, int], int | None] = field(default_factory=dict)
    figures: dict[int, ParticipantFigures] = field(default_factory=dict)
    session_counts: dict[int, SessionCounts] = field(default_factory=dict)

    @classmethod
    def of(cls, study: Study, pseudonymize: bool, secret: str | None) -> Context:
        ctx = cls(study, pseudonymize, secret)
        for change in study.changes:
            ctx.first_at.setdefault(change.participant_id, {}).setdefault(change.status, change.at)
        ctx.scrubbed = {p.id for p in study.participants if p.identifiers_scrubbed_at is not None}
        ctx.session_by_id = {x.id: x for x in study.sessions}
        ctx.position_of = {(x.participant_id, x.ordinal): x.position for x in study.sessions}
        by_participant = study_sessions_by_participant(study.sessions)
        ctx.figures = {
            p.id: participant_figures(
                p,
                by_participant.get(p.id, []),
                ctx.first_at.get(p.id, {}).get(ParticipantStatus.COMPLETED),
            )
            for p in study.participants
        }
        ctx.session_counts = _session_counts(study)
        return ctx

    def first(self, participant_id: int, status: str) -> datetime | None:
        """When the participant's status first became ``status``."""
        return self.first_at.get(participant_id, {}).get(status)

    def counts(self, session_id: int) -> SessionCounts:
        return self.session_counts.get(session_id, _NO_COUNTS)

    def session(self, session_id: int) -> LearningSession:
        return self.session_by_id[session_id]

    def platform_id(self, value: str | None, prefix: str, participant_id: int) -> str | None:
        """A worker or assignment id as exported: its pseudonym, unless the export is not
        pseudonymised or the participant's ids are pseudonyms already (scrubbed)."""
        if not self.pseudonymize or participant_id in self.scrubbed:
            return value
        assert self.secret is not None
        return pseudonym(self.secret, value, prefix)


def _session_counts(study: Study) -> dict[int, SessionCounts]:
    counts: dict[int, SessionCounts] = {}

    def of(session_id: int) -> SessionCounts:
        return counts.setdefault(session_id, SessionCounts())

    for event in study.events:
        if event.session_id is None:
            continue
        c = of(event.session_id)
        if event.record == Observed.DEMONSTRATION:
            c.demonstrated_actions += 1
        elif event.record == Observed.AGENT_STEP:
            c.agent_actions += 1
        elif event.record == Observed.FEEDBACK:
            c.feedback_given += 1
    for episode in study.episodes:
        if episode.ended_at is not None:
            c = of(episode.session_id)
            if episode.kind == EpisodeKind.DEMONSTRATION:
                c.demonstrations += 1
            elif episode.kind == EpisodeKind.AGENT:
                c.agent_episodes += 1
            else:
                raise ValueError(f"episode {episode.id} has an unknown kind {episode.kind!r}")
    for update in study.updates:
        c = of(update.session_id)
        c.final_normalized_return = update.normalized_return
        if update.update_index > 0:
            c.updates += 1
    return counts
