"""The learner updates' database work (blocking: the manager runs it in threads): the sessions
with pending updates, the next update's job (the learner's latest saved state and the events
since), and the outcome stored, or the failure counted."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from sqlalchemy import func, select

from server.app.storage.db import Database
from server.app.storage.models import Event, LearnerUpdate, LearningSession, utcnow
from server.app.storage.vocabulary import UpdateStatus
from server.app.updates.worker import records_of
from server.domains import definition

MAX_ATTEMPTS = 3  # a worker process dying this often on one update marks it failed


@dataclass
class Job:
    update_id: int
    session_id: int
    update_index: int
    environment: str
    payload: dict[str, Any]


class UpdateStore:
    """The ``learner_updates`` rows of the study's database."""

    def __init__(self, db: Database, learner_settings: Callable[[str], Any]) -> None:
        self.db = db
        self.learner_settings = learner_settings  # learner name -> settings dict

    def pending_sessions(self) -> list[int]:
        with self.db.read() as s:
            return list(
                s.scalars(
                    select(LearnerUpdate.session_id)
                    .where(LearnerUpdate.status == UpdateStatus.PENDING)
                    .group_by(LearnerUpdate.session_id)
                    .order_by(func.min(LearnerUpdate.queued_at))
                )
            )

    def processed(self, session_id: int) -> int:
        with self.db.read() as s:
            value = s.scalar(
                select(LearningSession.updates_processed).where(LearningSession.id == session_id)
            )
        return -1 if value is None else int(value)

    def load(self, session_id: int) -> Job | None:
        with self.db.read() as s:
            update = s.scalar(
                select(LearnerUpdate)
                .where(
                    LearnerUpdate.session_id == session_id,
                    LearnerUpdate.status == UpdateStatus.PENDING,
                )
                .order_by(LearnerUpdate.update_index)
                .limit(1)
            )
            if update is None:
                return None
            session = s.get(LearningSession, session_id)
            if session is None:
                return None  # erased since the update was read
            base = s.execute(
                select(LearnerUpdate.through_event_id, LearnerUpdate.learner_state)
                .where(
                    LearnerUpdate.session_id == session_id,
                    LearnerUpdate.status == UpdateStatus.DONE,
                    LearnerUpdate.learner_state.is_not(None),
                    LearnerUpdate.update_index < update.update_index,
                )
                .order_by(LearnerUpdate.update_index.desc())
                .limit(1)
            ).first()
            since = base.through_event_id if base is not None else 0
            rows = s.execute(
                select(
                    Event.record,
                    Event.task,
                    Event.state,
                    Event.action,
                    Event.next_state,
                    Event.feedback,
                    Event.stay_state,
                )
                .where(
                    Event.session_id == session_id,
                    Event.id > since,
                    Event.id <= update.through_event_id,
                )
                .order_by(Event.id)
            ).all()
            payload = {
                "environment": session.environment,
                "environment_spec": definition(session.environment),
                "learner": session.learner,
                "settings": self.learner_settings(session.learner),
                "seed": int(session.seed),
                "base_state": base.learner_state if base is not None else None,
                "records": records_of(rows),
                "fit": update.update_index > 0,
            }
            return Job(update.id, session_id, update.update_index, session.environment, payload)

    def commit(self, job: Job, outcome: dict[str, Any], deaths: int = 0) -> bool:
        """Store the update's outcome (after ``deaths`` processes died running it, each an
        attempt, as ``fail`` records one)."""
        with self.db.write() as s:
            update = s.get(LearnerUpdate, job.update_id)
            session = s.get(LearningSession, job.session_id)
            if update is None or session is None:
                return False  # the participant was erased while the update ran
            update.status = UpdateStatus.DONE
            update.finished_at = utcnow()
            update.attempts += 1 + deaths
            if deaths:
                update.error = "the update process died"
            for name in (
                "learner_state",
                "greedy_policy",
                "seconds",
                "objective",
                "steps",
                "normalized_return",
                "evaluation_seconds",
            ):
                setattr(update, name, outcome[name])
            session.updates_processed = max(session.updates_processed, job.update_index)
            session.policy_update = max(session.policy_update or 0, job.update_index)
            return session.updates_requested > session.updates_processed

    def fail(self, job: Job, error: str, retry: bool, attempts: int = 1) -> bool:
        with self.db.write() as s:
            update = s.get(LearnerUpdate, job.update_id)
            session = s.get(LearningSession, job.session_id)
            if update is None or session is None:
                return False  # the participant was erased while the update ran
            update.attempts += attempts
            update.error = error
            if retry and update.attempts < MAX_ATTEMPTS:
                return True
            update.status = UpdateStatus.FAILED
            update.finished_at = utcnow()
            session.updates_processed = max(session.updates_processed, job.update_index)
            return session.updates_requested > session.updates_processed
