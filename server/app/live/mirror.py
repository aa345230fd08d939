"""The one-way mirror: what a participant sees of their current session, as the dashboard
draws it (the grid, the task, the agent where it is, the agent's latest try, each +/-, the
learning curve after each update), or the attention check they are taking. Read only: nothing
here writes, so the participant can notice nothing; and no identifier (no platform id, no
completion code, not even the participant's number) is in the view.

``fingerprint`` is the cheap question asked every interval: the participant's status, their
latest event and their sessions' latest finished update; the view is read again only when it
changed.
"""

from __future__ import annotations

from typing import Any

from sqlalchemy import Connection, func, select

from server.app.participants import teaching, views
from server.app.storage.records import load, load_all
from server.app.storage.tables import EVENTS, PARTICIPANTS, SESSIONS, UPDATES
from server.app.storage.vocabulary import (
    FINISHED_STATUSES,
    Observed,
    ParticipantStatus,
    SessionKind,
    SessionStatus,
    UpdateStatus,
)
from server.app.study_file import StudyConfig
from server.domains import make as make_environment
from server.domains.base import ACTIONS

RECENT_EVENTS = 15  # the events listed under the grid, the latest first


def fingerprint(c: Connection, participant_id: int) -> tuple[Any, ...]:
    """What changes whenever the participant's view does (one query)."""
    sessions = select(SESSIONS.c.id).where(SESSIONS.c.participant_id == participant_id)
    finished = (UPDATES.c.session_id.in_(sessions), UPDATES.c.status != UpdateStatus.PENDING)
    row = c.execute(
        select(
            select(PARTICIPANTS.c.status)
            .where(PARTICIPANTS.c.id == participant_id)
            .scalar_subquery(),
            select(func.max(EVENTS.c.id))
            .where(EVENTS.c.participant_id == participant_id)
            .scalar_subquery(),
            select(func.max(UPDATES.c.finished_at)).where(*finished).scalar_subquery(),
            select(func.count()).select_from(UPDATES).where(*finished).scalar_subquery(),
        )
    ).one()
    return tuple(row)


def mirror_view(c: Connection, study: StudyConfig, participant_id: int) -> dict[str, Any] | None:
    """What the participant sees now; None when there is no such participant."""
    participant = load(c, PARTICIPANTS, PARTICIPANTS.c.id == participant_id)
    if participant is None:
        return None
    sessions = load_all(
        c, SESSIONS, SESSIONS.c.participant_id == participant.id, order_by=SESSIONS.c.ordinal
    )
    of = sum(1 for x in sessions if x.kind == SessionKind.STUDY)
    active = next((x for x in sessions if x.status == SessionStatus.ACTIVE), None)
    check = views.attention_check(c, participant)
    status = ParticipantStatus(participant.status)
    view: dict[str, Any] = {
        "status": str(status),
        "finished": status in FINISHED_STATUSES,
        "agents": of,
        "check": None if check is None else check.model_dump(mode="json"),
        "session": None,
    }
    if active is None or check is not None:
        return view
    view["session"] = session_view(c, study, active, of)
    return view


def session_view(c: Connection, study: StudyConfig, session: Any, of: int) -> dict[str, Any]:
    env = make_environment(session.environment)
    state = teaching.teaching_state(session, env).model_dump(mode="json")
    state.pop("session_id", None)
    events = c.execute(
        select(
            EVENTS.c.id,
            EVENTS.c.kind,
            EVENTS.c.created_at,
            EVENTS.c.mode,
            EVENTS.c.task,
            EVENTS.c.state,
            EVENTS.c.action,
            EVENTS.c.next_state,
            EVENTS.c.feedback,
            EVENTS.c.record,
            EVENTS.c.episode_index,
            EVENTS.c.episode_end,
        )
        .where(EVENTS.c.session_id == session.id)
        .order_by(EVENTS.c.id.desc())
        .limit(200)
    ).all()
    # The agent's latest try: the steps of its latest episode, and the feedback given since its
    # first step (feedback events carry no episode: each is on the agent step before it).
    latest_try: list[dict[str, Any]] = []
    feedback: list[dict[str, Any]] = []
    try_episode = None
    for event in events:  # the newest first
        if event.record == Observed.AGENT_STEP:
            if try_episode is None:
                try_episode = event.episode_index
            if event.episode_index != try_episode:
                break
            latest_try.append(
                {
                    "state": event.state,
                    "action": None if event.action is None else ACTIONS[event.action],
                    "next": event.next_state,
                }
            )
        elif event.record == Observed.FEEDBACK:
            feedback.append({"feedback": int(event.feedback)})
    if try_episode is None:
        feedback = []
    curve = c.execute(
        select(UPDATES.c.update_index, UPDATES.c.episodes, UPDATES.c.normalized_return)
        .where(UPDATES.c.session_id == session.id, UPDATES.c.status == UpdateStatus.DONE)
        .order_by(UPDATES.c.update_index)
    ).all()
    totals = c.execute(
        select(
            func.count().filter(EVENTS.c.feedback > 0),
            func.count().filter(EVENTS.c.feedback < 0),
        ).where(EVENTS.c.session_id == session.id, EVENTS.c.record == Observed.FEEDBACK)
    ).one()
    return {
        "kind": session.kind,
        "agent": None if session.position is None else int(session.position) + 1,
        "of": of,
        "environment": teaching.environment_description(session.environment, reveal_gravity=True),
        "learner": session.learner,
        "colour": {"name": session.colour_name, "hex": session.colour_hex},
        "teaching": state,
        "latest_try": latest_try[::-1],
        "try_feedback": feedback[::-1],
        "feedback_given": {"good": int(totals[0]), "bad": int(totals[1])},
        "recent": [
            {
                "kind": e.kind,
                "at": e.created_at.isoformat(),
                "mode": e.mode,
                "task": e.task,
                "action": None if e.action is None else ACTIONS[e.action],
                "feedback": e.feedback if e.record == Observed.FEEDBACK else None,
                "record": e.record,
                "episode_end": e.episode_end,
            }
            for e in events[:RECENT_EVENTS]
        ],
        "curve": [
            {
                "update": u.update_index,
                "episodes": u.episodes,
                "normalized_return": u.normalized_return,
            }
            for u in curve
        ],
    }
