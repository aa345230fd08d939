"""The learner updates' database work (blocking: the manager runs it in threads): the sessions
with pending updates, the next update's job (the learner's latest saved state and the events
since), and the outcome stored, or the failure counted.

Several servers may share the database. Reading an update's job claims it: the row is locked
(``FOR UPDATE SKIP LOCKED`` on PostgreSQL, so servers claiming at once do not wait for each
other; SQLite has one server and one writer) and takes this server's name with a lease, which
the server renews while it runs (``renew``). An update whose claim is another live server's is
left to it; one whose lease expired (its server died) is taken over. The outcome is stored only
by the claim that holds the update (this server, the run it counted): a server that lost its
claim (its lease expired while it was stalled, and another took the update) stores nothing, so
each update's result is stored once. ``runs`` counts the claims taken on an update.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import Any

from sqlalchemy import func, or_, select, update
from sqlalchemy.orm import Session, aliased

from server.app.storage.db import Database
from server.app.storage.models import Event, LearnerUpdate, LearningSession, utcnow
from server.app.storage.vocabulary import UpdateStatus
from server.app.updates.worker import records_of
from server.domains import definition

MAX_ATTEMPTS = 3  # a worker process dying this often on one update marks it failed
LEASE_SECONDS = 30.0  # a claim's lease, renewed every third of it while its server lives


@dataclass
class Job:
    update_id: int
    session_id: int
    update_index: int
    environment: str
    payload: dict[str, Any]
    run: int = 1  # the claim's number among the update's runs (``LearnerUpdate.runs``)


@dataclass(frozen=True)
class Stored:
    """What storing an update's end did: ``stored`` False where this server no longer held
    the update's claim (another server took it over: its result is the one kept); ``more``:
    the session has further updates pending for this server to run."""

    stored: bool
    more: bool


@dataclass(frozen=True)
class PendingSession:
    """A session whose next update no live claim holds, and who awaits it (None: nobody)."""

    session_id: int
    awaited_since: float | None  # seconds since the epoch
    awaited_update: int | None


class UpdateStore:
    """The ``learner_updates`` rows of the study's database."""

    def __init__(
        self,
        db: Database,
        learner_settings: Callable[[str], Any],
        server: str = "server",
        lease_seconds: float = LEASE_SECONDS,
        channel: str | None = None,
    ) -> None:
        self.db = db
        self.learner_settings = learner_settings  # learner name -> settings dict
        self.server = server  # this server's name in the claims (``servers``)
        self.lease = timedelta(seconds=lease_seconds)
        # PostgreSQL's notification channel of the deployment (``notices``): a stored outcome
        # is announced in its own transaction, so the other servers' waiters go on.
        self.channel = channel

    def pending_sessions(self) -> list[PendingSession]:
        """Sessions with pending updates that no live claim holds (unclaimed, or their
        server's lease expired), the longest queued first."""
        now = utcnow()
        held = aliased(LearnerUpdate)
        free = or_(LearnerUpdate.claimed_by.is_(None), LearnerUpdate.lease_until < now)
        # A session one of whose updates a live claim holds is its server's (the next ones
        # need that one's learner).
        claimed = (
            select(held.id)
            .where(
                held.session_id == LearnerUpdate.session_id,
                held.status == UpdateStatus.PENDING,
                held.claimed_by.is_not(None),
                held.lease_until >= now,
            )
            .exists()
        )
        with self.db.read() as s:
            rows = s.execute(
                select(
                    LearnerUpdate.session_id,
                    LearningSession.awaited_since,
                    LearningSession.awaited_update,
                )
                .join(LearningSession, LearningSession.id == LearnerUpdate.session_id)
                .where(LearnerUpdate.status == UpdateStatus.PENDING, free, ~claimed)
                .group_by(
                    LearnerUpdate.session_id,
                    LearningSession.awaited_since,
                    LearningSession.awaited_update,
                )
                .order_by(func.min(LearnerUpdate.queued_at))
            ).all()
        return [
            PendingSession(
                row.session_id,
                row.awaited_since.timestamp() if row.awaited_since is not None else None,
                row.awaited_update,
            )
            for row in rows
        ]

    def renew(self) -> int:
        """Extend the leases of this server's claims; how many it holds."""
        with self.db.write() as s:
            result = s.execute(
                update(LearnerUpdate)
                .where(
                    LearnerUpdate.claimed_by == self.server,
                    LearnerUpdate.status == UpdateStatus.PENDING,
                )
                .values(lease_until=utcnow() + self.lease)
            )
            return int(result.rowcount)  # type: ignore[attr-defined]

    def release_all(self, every_server: bool = False) -> None:
        """Give up this server's claims on pending updates (it stops: another server, or
        this one restarted, takes them at once); ``every_server``: everyone's (SQLite, where
        a starting server is the only one)."""
        with self.db.write() as s:
            query = update(LearnerUpdate).where(LearnerUpdate.status == UpdateStatus.PENDING)
            if not every_server:
                query = query.where(LearnerUpdate.claimed_by == self.server)
            s.execute(query.values(claimed_by=None, lease_until=None))

    def release(self, job: Job) -> None:
        """Give up the claim of a job that did not run (the cluster was unreachable)."""
        with self.db.write() as s:
            s.execute(
                update(LearnerUpdate)
                .where(
                    LearnerUpdate.id == job.update_id,
                    LearnerUpdate.claimed_by == self.server,
                    LearnerUpdate.runs == job.run,
                    LearnerUpdate.status == UpdateStatus.PENDING,
                )
                .values(claimed_by=None, lease_until=None, runs=LearnerUpdate.runs - 1)
            )

    def await_update(self, session_id: int, target: int, since: float) -> None:
        """Someone waits (since ``since``, seconds since the epoch) for the session's update
        ``target``: stored for every server's queue, and announced."""
        with self.db.write() as s:
            session = s.get(LearningSession, session_id)
            if session is None or session.updates_processed >= target:
                return
            if session.awaited_since is None:
                session.awaited_since = datetime.fromtimestamp(since, UTC)
            session.awaited_update = max(session.awaited_update or -1, target)
            self._announce(s, {"awaited": session_id, "update": target, "since": since})

    def processed(self, session_id: int) -> int:
        with self.db.read() as s:
            value = s.scalar(
                select(LearningSession.updates_processed).where(LearningSession.id == session_id)
            )
        return -1 if value is None else int(value)

    def load(self, session_id: int) -> Job | None:
        """The session's next update's job, claimed by this server; None where it has none
        pending, or another live server's claim holds it (or it is being claimed). The claim
        is a short write of its own; the job is read after it (on SQLite, participants' writes
        do not wait for the read of an update's events)."""
        claimed = self._claim(session_id)
        if claimed is None:
            return None
        update_id, run = claimed
        with self.db.read() as s:
            update = s.get(LearnerUpdate, update_id)
            session = s.get(LearningSession, session_id)
            if update is None or session is None:
                return None  # erased since the update was claimed
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
            return Job(
                update.id,
                session_id,
                update.update_index,
                session.environment,
                payload,
                run=run,
            )

    def _claim(self, session_id: int) -> tuple[int, int] | None:
        """Claim the session's next pending update for this server: its id and the claim's
        run number; None where another live claim holds it or it is being claimed."""
        with self.db.write() as s:
            update = s.scalar(
                select(LearnerUpdate)
                .where(
                    LearnerUpdate.session_id == session_id,
                    LearnerUpdate.status == UpdateStatus.PENDING,
                )
                .order_by(LearnerUpdate.update_index)
                .limit(1)
                .with_for_update(skip_locked=True)
            )
            if update is None:
                return None
            earlier = s.scalar(
                select(func.count())
                .select_from(LearnerUpdate)
                .where(
                    LearnerUpdate.session_id == session_id,
                    LearnerUpdate.status == UpdateStatus.PENDING,
                    LearnerUpdate.update_index < update.update_index,
                )
            )
            if earlier:
                return None  # the session's next update is being claimed by another server
            now = utcnow()
            holder = update.claimed_by
            if holder not in (None, self.server) and update.lease_until is not None:
                if update.lease_until >= now:
                    return None  # another server runs it
                update.taken_from = holder
            update.claimed_by = self.server
            update.lease_until = now + self.lease
            update.runs += 1
            return update.id, update.runs

    def _held(self, s: Session, job: Job) -> tuple[LearnerUpdate, LearningSession] | None:
        """The job's update and session, locked, where this server's claim still holds the
        update; None where it does not (another server took it over) or they were erased."""
        update = s.get(LearnerUpdate, job.update_id, with_for_update=True)
        session = s.get(LearningSession, job.session_id)
        if update is None or session is None:
            return None  # the participant was erased while the update ran
        if (
            update.status != UpdateStatus.PENDING
            or update.claimed_by != self.server
            or update.runs != job.run
        ):
            return None
        return update, session

    def _processed(self, s: Session, session: LearningSession, index: int) -> bool:
        """The session's updates through ``index`` are processed: its waiters on every server
        go on. Whether it has more pending."""
        session.updates_processed = max(session.updates_processed, index)
        if session.awaited_update is not None and session.awaited_update <= index:
            session.awaited_since = session.awaited_update = None
        self._announce(s, {"processed": session.id, "update": session.updates_processed})
        return session.updates_requested > session.updates_processed

    def _announce(self, s: Session, notice: dict[str, Any]) -> None:
        """A notice to every server, sent when the transaction commits (PostgreSQL)."""
        if self.channel is not None:
            payload = json.dumps({**notice, "from": self.server})
            s.execute(select(func.pg_notify(self.channel, payload)))

    def announce_pending(self, session_ids: list[int]) -> None:
        """Tell the other servers these sessions have new pending updates."""
        with self.db.write() as s:
            self._announce(s, {"pending": session_ids})

    def commit(self, job: Job, outcome: dict[str, Any], deaths: int = 0) -> Stored:
        """Store the update's outcome (after ``deaths`` processes died running it, each an
        attempt, as ``fail`` records one), if this server's claim still holds the update."""
        with self.db.write() as s:
            held = self._held(s, job)
            if held is None:
                return Stored(stored=False, more=False)
            update, session = held
            update.status = UpdateStatus.DONE
            update.lease_until = None
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
            session.policy_update = max(session.policy_update or 0, job.update_index)
            return Stored(stored=True, more=self._processed(s, session, job.update_index))

    def fail(self, job: Job, error: str, retry: bool, attempts: int = 1) -> bool:
        """Count the failed attempts; the update stays pending (its claim given up) while
        ``retry`` allows another, else it failed. Whether this server should go on with the
        session (False also where its claim was lost)."""
        with self.db.write() as s:
            held = self._held(s, job)
            if held is None:
                return False
            update, session = held
            update.attempts += attempts
            update.error = error
            if retry and update.attempts < MAX_ATTEMPTS:
                update.claimed_by = update.lease_until = None
                return True
            update.status = UpdateStatus.FAILED
            update.finished_at = utcnow()
            update.lease_until = None
            return self._processed(s, session, job.update_index)
