"""The live funnel: every participant's stage, how long they have been there, whether they have
been idle too long or failed an attention check, in one read of the database (so that the
counts are those of one moment), with the learner updates' queue.

A participant's stage is their status, made finer while they teach: the tutorial, agent k of
n, waiting for an update (the agent's turn, its learner still updating) or an attention check.
"""

from __future__ import annotations

from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import Connection, func, select

from server.app.storage.tables import CHECKS, PARTICIPANTS, SESSIONS, STATUS_CHANGES, UPDATES
from server.app.storage.vocabulary import (
    IN_PROGRESS,
    CheckStatus,
    ExclusionMark,
    Mode,
    ParticipantStatus,
    SessionKind,
    SessionStatus,
    UpdateStatus,
)

# No request for longer than this: idle too long (the page is open and nothing happens, or the
# participant has gone; the sweep marks them abandoned after BAM_ABANDON_MINUTES).
IDLE_MINUTES = 5.0
# The rows listed: the participants in progress (and those waiting), the longest there first.
MAX_ROWS = 500

# The stages, in the order of the flow; each stage's label says it as the dashboard does.
STAGES: dict[str, str] = {
    "waiting": "Waiting for a place",
    "consent": "Consent (device check)",
    "instructions": "Instructions",
    "tutorial": "Tutorial",
    "agent": "Teaching agent k of n",
    "updating": "Waiting for an update",
    "attention_check": "Attention check",
    "questionnaire": "Questionnaire",
    "done": "Done",
    "declined": "Declined consent",
    "incompatible": "Turned away by the device check",
    "returned": "Returned",
    "abandoned": "Abandoned (idle too long)",
}
OF_STATUS = {
    ParticipantStatus.WAITING: "waiting",
    ParticipantStatus.ARRIVED: "consent",
    ParticipantStatus.CONSENTED: "instructions",
    ParticipantStatus.QUESTIONNAIRE: "questionnaire",
    ParticipantStatus.COMPLETED: "done",
    ParticipantStatus.SUBMITTED: "done",
    ParticipantStatus.DECLINED: "declined",
    ParticipantStatus.INCOMPATIBLE: "incompatible",
    ParticipantStatus.RETURNED: "returned",
    ParticipantStatus.ABANDONED: "abandoned",
}
LISTED = (*IN_PROGRESS, ParticipantStatus.WAITING)


def _seconds(now: datetime, since: datetime | None) -> float | None:
    return None if since is None else round(max(0.0, (now - since).total_seconds()), 1)


def _active_sessions(c: Connection) -> dict[int, Any]:
    """Each participant's active learning session (its row), by participant."""
    s = SESSIONS.c
    return {
        row.participant_id: row
        for row in c.execute(
            select(
                s.id,
                s.participant_id,
                s.kind,
                s.position,
                s.mode,
                s.started_at,
                s.updates_requested,
                s.updates_processed,
            ).where(s.status == SessionStatus.ACTIVE)
        )
    }


def _stage(
    status: ParticipantStatus,
    since: datetime | None,
    session: Any,
    check: tuple[bool, datetime | None],
    pending: dict[int, datetime],
) -> tuple[str, datetime | None, int | None]:
    """A participant's stage, since when they are in it, and the agent (from 1) they teach:
    their status's stage, made finer while they teach (``check``: whether they take an
    attention check, and when it began)."""
    if status not in (ParticipantStatus.TUTORIAL, ParticipantStatus.TEACHING):
        return OF_STATUS[status], since, None
    in_check, check_started = check
    if in_check:
        return "attention_check", check_started or since, None
    if session is not None and session.mode == Mode.AGENT and session.id in pending:
        return "updating", pending[session.id], None
    if session is not None and session.kind == SessionKind.STUDY:
        return "agent", session.started_at or since, int(session.position) + 1
    return "tutorial", (session.started_at or since) if session is not None else since, None


def funnel(c: Connection, now: datetime) -> dict[str, Any]:
    """The funnel at ``now``, from the database as ``c`` reads it (one transaction: the counts of
    one moment): ``stages`` (participants per stage; ``agents``: per agent k while teaching),
    ``statuses`` (per status), ``participants`` (those in progress or waiting: stage, since,
    idle, failed checks) and ``updates`` (pending, the oldest's wait)."""
    p, s, k, u = PARTICIPANTS.c, SESSIONS.c, CHECKS.c, UPDATES.c
    people = c.execute(select(p.id, p.status, p.last_seen_at, p.created_at)).all()
    changed = dict(
        c.execute(
            select(STATUS_CHANGES.c.participant_id, func.max(STATUS_CHANGES.c.at))
            .where(STATUS_CHANGES.c.status.not_in(tuple(ExclusionMark)))
            .group_by(STATUS_CHANGES.c.participant_id)
        ).all()
    )
    agents_of: dict[int, int] = dict(
        c.execute(
            select(s.participant_id, func.count())
            .where(s.kind == SessionKind.STUDY)
            .group_by(s.participant_id)
        ).all()
    )
    active = _active_sessions(c)
    checking = dict(
        c.execute(
            select(k.participant_id, k.started_at).where(k.status == CheckStatus.ACTIVE)
        ).all()
    )
    failed: dict[int, int] = dict(
        c.execute(
            select(k.participant_id, func.count())
            .where(k.status == CheckStatus.FAILED)
            .group_by(k.participant_id)
        ).all()
    )
    pending = dict(
        c.execute(
            select(u.session_id, func.min(u.queued_at))
            .where(u.status == UpdateStatus.PENDING)
            .group_by(u.session_id)
        ).all()
    )
    stages = dict.fromkeys(STAGES, 0)
    statuses = dict.fromkeys((str(x) for x in ParticipantStatus), 0)
    agents: dict[int, int] = {}
    rows = []
    idle_before = now - timedelta(minutes=IDLE_MINUTES)
    for person in people:
        status = ParticipantStatus(person.status)
        statuses[status] += 1
        since = changed.get(person.id, person.created_at)
        session = active.get(person.id)
        check = (person.id in checking, checking.get(person.id))
        stage, since, agent = _stage(status, since, session, check, pending)
        if agent is not None:
            agents[agent] = agents.get(agent, 0) + 1
        stages[stage] += 1
        if status in LISTED:
            rows.append(
                {
                    "participant_id": person.id,
                    "status": str(status),
                    "stage": stage,
                    "agent": agent,
                    "agents": agents_of.get(person.id, 0),
                    "seconds_there": _seconds(now, since),
                    "idle_seconds": _seconds(now, person.last_seen_at),
                    "idle": status in IN_PROGRESS and person.last_seen_at < idle_before,
                    "failed_checks": failed.get(person.id, 0),
                    "session_id": session.id if session is not None else None,
                }
            )
    rows.sort(key=lambda row: -(row["seconds_there"] or 0.0))
    oldest = min(pending.values(), default=None)
    return {
        "at": now.isoformat(),
        "participants_total": len(people),
        "stages": stages,
        "agents": {str(number): agents[number] for number in sorted(agents)},
        "statuses": statuses,
        "idle": sum(1 for row in rows if row["idle"]),
        "failed_a_check": sum(1 for person in people if failed.get(person.id)),
        "participants": rows[:MAX_ROWS],
        "listed_of": len(rows),
        "updates": {
            "pending": int(
                c.scalar(select(func.count()).where(u.status == UpdateStatus.PENDING)) or 0
            ),
            "sessions_pending": len(pending),
            "oldest_wait_seconds": _seconds(now, oldest),
        },
    }
