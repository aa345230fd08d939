"""The participants' + and - feedback in the unpaired-preference shape that preference
trainers read (one labelled completion per row, as TRL's KTO takes it): the state and the
trajectory so far, the agent's action, and the label. Built from the export's events,
episodes and sessions: a feedback event applies to the session's latest agent step, as the
learner's ``record_feedback`` keeps it (``export.minari`` reads the same rule)."""

from __future__ import annotations

from typing import Any

import pandas as pd

from server.app.export.columns import BOOL, INT, SESSION_COLUMNS, Column
from server.app.export.release import SESSION_FILES

FEEDBACK = (
    Column("event_id", "The feedback event (events.csv event_id).", INT),
    Column("step_event_id", "The agent step it judges (events.csv event_id).", INT),
    Column("participant_id", "The participant who gave it (participants.csv).", INT),
    Column("session_id", "The learning session (sessions.csv); empty for a tutorial's.", INT),
    Column(
        "tutorial_session_id",
        "The tutorial's learning session (tutorial_sessions.csv); empty for a study session's.",
        INT,
    ),
    Column("session_kind", "study (session_id is given) or tutorial (tutorial_session_id is)."),
    Column("environment", "The environment taught."),
    Column("learner", "The session's learner."),
    Column("episode_id", "The agent episode of the step (episodes.csv).", INT),
    Column("task", "Index of the episode's task.", INT),
    Column("task_name", "Name of that task."),
    Column(
        "states",
        "The episode's states so far, its first to the one the agent acted in (a list).",
    ),
    Column("actions", "The agent's actions before this one in the episode (a list)."),
    Column("state", "The state the agent acted in.", INT),
    Column("action", "The agent's action: STAY, UP, DOWN, LEFT or RIGHT."),
    Column("next_state", "The state the action led to.", INT),
    Column(
        "prompt",
        "The state and trajectory so far as text (environment, task, then state action ... "
        "state), for trainers that read a prompt.",
    ),
    Column("completion", "The agent's action (as in action), the completion judged."),
    Column("label", "True for + (desirable), False for - (undesirable).", BOOL),
    Column("feedback", "+1 or -1, as in events.csv.", INT),
)
LIST_COLUMNS = {"states": "int64", "actions": "string"}
DESCRIPTION = (
    "One row per + or - a participant gave on an agent's step, in the unpaired-preference "
    "shape (prompt, completion, label) with the state and trajectory so far; built from "
    "events.csv, episodes.csv and the sessions."
)


def _prompt(row: dict[str, Any]) -> str:
    moves = " ".join(
        f"{state} {action}" for state, action in zip(row["states"], row["actions"], strict=False)
    )
    path = f"{moves} {row['state']}" if moves else str(row["state"])
    return f"environment {row['environment']}, task {row['task_name']}: {path}"


def _session_of(row: Any) -> int | None:
    """An episode's or an event's learning session, of either kind (``SESSION_COLUMNS``: the
    ids are one sequence); None for an event outside the sessions."""
    given = [getattr(row, name) for name in SESSION_COLUMNS.values()]
    found = [int(value) for value in given if not pd.isna(value)]
    return found[0] if found else None


def feedback_frame(tables: dict[str, pd.DataFrame]) -> pd.DataFrame:
    """The feedback table of the export's ``tables``, in the order the feedback was given."""
    sessions = pd.concat(
        [tables[SESSION_FILES[kind]].assign(session_kind=kind.value) for kind in SESSION_FILES]
    ).set_index("session_id")
    episodes = {
        (_session_of(e), int(e.index)): e for e in tables["episodes"].itertuples(index=False)
    }
    trajectory: dict[tuple[int, int], tuple[list[int], list[str]]] = {}
    latest: dict[int, dict[str, Any]] = {}
    rows: list[dict[str, Any]] = []
    for event in tables["events"].itertuples(index=False):
        session_id = _session_of(event)
        if session_id is None:
            continue
        if event.record in ("demonstration", "agent_step"):
            key = (session_id, int(event.episode_index))
            states, actions = trajectory.setdefault(key, ([], []))
            if event.record == "agent_step":
                session = sessions.loc[session_id]
                episode = episodes[key]
                latest[session_id] = {
                    "step_event_id": int(event.event_id),
                    "participant_id": int(event.participant_id),
                    **{
                        name: session_id if kind == session["session_kind"] else None
                        for kind, name in SESSION_COLUMNS.items()
                    },
                    "session_kind": session["session_kind"],
                    "environment": session["environment"],
                    "learner": session["learner"],
                    "episode_id": int(episode.episode_id),
                    "task": int(episode.task),
                    "task_name": episode.task_name,
                    "states": [*states, int(event.state)],
                    "actions": list(actions),
                    "state": int(event.state),
                    "action": event.action,
                    "next_state": int(event.next_state),
                }
            states.append(int(event.state))
            actions.append(event.action)
        elif event.record == "feedback":
            if session_id not in latest:
                raise ValueError(
                    f"event {event.event_id}: feedback in session {session_id} with no agent "
                    "step before it"
                )
            given = int(event.feedback)
            row = {**latest[session_id], "event_id": int(event.event_id), "feedback": given}
            rows.append(
                {**row, "prompt": _prompt(row), "completion": row["action"], "label": given > 0}
            )
    frame = pd.DataFrame(rows, columns=[column.name for column in FEEDBACK])
    for column in FEEDBACK:
        if column.kind == INT:
            frame[column.name] = frame[column.name].astype("Int64")
    return frame
