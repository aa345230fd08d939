"""The server's capacity held on Prolific too, after publishing: the study's
``max_concurrent_submissions`` follows the participants the server admits at once (its study
file's limit or its live measured capacity), and the server pauses the study by itself while
its update queue makes agents wait, and starts it again once the queue has drained.

Prolific keeps sending participants up to ``max_concurrent_submissions`` whatever the server's
own line says; where the live capacity falls below it (a slower machine than measured, more
of the server's own work), the line grows and agents wait. Each change is sent with Prolific's
API (``PATCH /studies/{id}/`` with ``submissions_config``; the PAUSE and START transitions) and
logged in ``prolific_study_changes`` with why and Prolific's answer, which the dashboard shows.
Only a pause the server made is undone by it: a study the researcher paused stays paused.

``changes_for`` is the rule, on plain readings (``Load``); ``follow`` reads the study on
Prolific, applies the rule and logs what it did. The server's own loop (``routers/prolific.py``)
gives it the readings of the update queue and the places."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from sqlalchemy import select

from server.app.platforms.prolific import ProlificClient
from server.app.platforms.prolific_sync import record_study_status
from server.app.platforms.review import ReviewRefused, ReviewUnavailable
from server.app.storage.db import Database
from server.app.storage.models import ProlificStudy, ProlificStudyChange, utcnow

# An agent step that has waited this long for its learner's update, in two readings in a row
# (``steady``): the queue makes agents wait (an update takes a fraction of a second on an idle
# slot, and a single slow one is not a queue).
PAUSE_WAIT_SECONDS = 5.0
MAX_CONCURRENT = "max_concurrent_submissions"
FOLLOWED = ("ACTIVE", "PAUSED")


@dataclass(frozen=True)
class Load:
    """The server's readings: how many it admits at once (None: not known yet), the sessions
    whose participant waits for an update and the longest such wait, and the participants in
    its line for a place."""

    limit: int | None
    awaited: int
    oldest_wait_seconds: float
    waiting: int

    @property
    def overloaded(self) -> bool:
        # The server's line alone is not: it is Prolific sending more than the server admits,
        # which the concurrency set to the limit ends.
        return self.awaited > 0 and self.oldest_wait_seconds >= PAUSE_WAIT_SECONDS

    @property
    def drained(self) -> bool:
        return self.waiting == 0 and self.awaited == 0


@dataclass(frozen=True)
class Change:
    change: str  # MAX_CONCURRENT, PAUSE or START
    value: int | None
    reason: str


def steady(previous: Load | None, now: Load) -> Load:
    """``now``, its wait for updates only what the reading before also showed (none on the
    first): a pause answers a queue that lasts, not a moment's."""
    if previous is None:
        return Load(now.limit, 0, 0.0, now.waiting)
    return Load(
        now.limit,
        min(previous.awaited, now.awaited),
        min(previous.oldest_wait_seconds, now.oldest_wait_seconds),
        now.waiting,
    )


def concurrency_of(study: dict[str, Any]) -> int | None:
    """The study's ``max_concurrent_submissions`` (None: no limit)."""
    config = study.get("submissions_config") or {}
    limit = config.get("max_concurrent_submissions") if isinstance(config, dict) else None
    return limit if isinstance(limit, int) and limit >= 1 else None


def changes_for(
    status: str, concurrency: int | None, load: Load, paused_by_us: bool
) -> list[Change]:
    """What the server changes on a study that is ``status`` on Prolific with ``concurrency``
    at once, given its ``load``; ``paused_by_us``: the server's own pause holds it."""
    if status not in FOLLOWED:
        return []
    changes = []
    if load.limit is not None and concurrency != load.limit:
        changes.append(
            Change(
                MAX_CONCURRENT,
                load.limit,
                f"the server admits {load.limit} participant(s) at once (Prolific had "
                f"{concurrency if concurrency is not None else 'no limit'})",
            )
        )
    if status == "ACTIVE" and load.overloaded:
        why = (
            f"{load.awaited} participant(s) waiting for their agent's update, the longest "
            f"{load.oldest_wait_seconds:.0f} s"
        )
        changes.append(Change("PAUSE", None, f"the update queue makes agents wait: {why}"))
    elif status == "PAUSED" and paused_by_us and load.drained:
        changes.append(
            Change(
                "START",
                None,
                "the update queue has drained (no one waits for an agent or for a place)",
            )
        )
    return changes


def paused_by_server(db: Database, study_id: str) -> bool:
    """Whether the study's last pause or start that Prolific took was the server's PAUSE."""
    with db.read() as s:
        last = s.scalar(
            select(ProlificStudyChange.change)
            .where(
                ProlificStudyChange.study_id == study_id,
                ProlificStudyChange.change.in_(("PAUSE", "START")),
                ProlificStudyChange.outcome == "done",
            )
            .order_by(ProlificStudyChange.id.desc())
            .limit(1)
        )
    return last == "PAUSE"


def follow(db: Database, client: ProlificClient, study_id: str, load: Load) -> list[Change]:
    """Bring the study on Prolific in line with the server's ``load``; each change made (or
    refused) is logged. The changes Prolific took."""
    study = client.get_study(study_id)
    status = str(study.get("status"))
    planned = changes_for(status, concurrency_of(study), load, paused_by_server(db, study_id))
    made = []
    for change in planned:
        try:
            if change.change == MAX_CONCURRENT:
                assert change.value is not None
                client.set_max_concurrent(study_id, change.value)
            else:
                answer = client.transition_study(study_id, change.change)
                record_study_status(db, study_id, str(answer.get("status")), utcnow())
        except (ReviewRefused, ReviewUnavailable) as error:
            outcome = str(error)
        else:
            outcome = "done"
            made.append(change)
        with db.write() as s:
            s.add(
                ProlificStudyChange(
                    study_id=study_id,
                    at=utcnow(),
                    change=change.change,
                    value=change.value,
                    reason=change.reason,
                    outcome=outcome,
                )
            )
    return made


def followed_studies(db: Database) -> list[str]:
    """The Prolific studies the server follows: those its events say are ACTIVE or PAUSED."""
    with db.read() as s:
        return list(
            s.scalars(
                select(ProlificStudy.study_id)
                .where(ProlificStudy.status.in_(FOLLOWED))
                .order_by(ProlificStudy.study_id)
            )
        )


def changes_of(db: Database, study_id: str, last: int = 20) -> list[ProlificStudyChange]:
    """The study's last changes made by the server, newest first."""
    with db.read() as s:
        return list(
            s.scalars(
                select(ProlificStudyChange)
                .where(ProlificStudyChange.study_id == study_id)
                .order_by(ProlificStudyChange.id.desc())
                .limit(last)
            )
        )
