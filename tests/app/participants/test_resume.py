"""A participant who refreshes, reconnects, or comes back after the server restarted continues
exactly where they were, learner included."""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from server.app.main import create_app
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import LearnerUpdate
from server.app.study_file import StudyConfig
from server.domains import make
from server.domains.base import ACTIONS
from server.teacher import Teacher
from tests.support.server import (
    Participant,
    arrive,
    study_config,
    teaching_participant,
    wait_for_updates,
)

# Two Rooms, task A: every study start is at least twelve moves from its goal.
TWO_ROOMS = {
    "domains": [{"name": "navigation", "environments": ["two-rooms"]}],
    "tutorial": {"enabled": False},
}


@pytest.fixture
def study() -> StudyConfig:
    return study_config(**TWO_ROOMS)


def start_demonstration(
    participant: Participant, session_id: int, moves: int
) -> tuple[Teacher, int]:
    base = participant.session(session_id)
    view = participant.get(base)
    env = make(view["summary"]["environment"])
    teacher = Teacher(env, seed=1)
    state = participant.act(f"{base}/reset")["session"]["agent"]["state"]
    participant.act(f"{base}/mode", mode="demonstrate")
    for _ in range(moves):
        state = participant.act(f"{base}/move", action=ACTIONS[teacher.next_action(0, state)])[
            "session"
        ]["agent"]["state"]
    return teacher, state


def finish_demonstration(
    participant: Participant, session_id: int, teacher: Teacher, state: int
) -> dict:
    base = participant.session(session_id)
    for _ in range(200):
        data = participant.act(f"{base}/move", action=ACTIONS[teacher.next_action(0, state)])
        state = data["session"]["agent"]["state"]
        if data["outcome"]["episode_ended"]:
            return data
    raise AssertionError("the demonstration did not reach the goal")


def test_a_refresh_mid_episode_shows_everything_as_it_was(client: TestClient, db: Database) -> None:
    participant, session_id = teaching_participant(client)
    teacher, state = start_demonstration(participant, session_id, 2)
    # The reloaded page knows only the cookie: it reads where the participant is.
    me = client.get("/api/participant").json()
    assert me["current_session_id"] == session_id and me["next_seq"] == participant.seq
    view = client.get(f"/api/sessions/{session_id}").json()
    teaching = view["teaching"]
    assert teaching["mode"] == "demonstrate" and teaching["agent"]["state"] == state
    assert teaching["episode"] == {"index": 0, "kind": "demonstration", "task": 0, "actions": 2}
    resumed = Participant(client, participant.token, view["participant"]["next_seq"])
    ended = finish_demonstration(resumed, session_id, teacher, state)
    assert ended["session"]["episodes"] == 1
    assert ended["session"]["actions"] > 2  # the same episode went on


def test_reconnecting_without_the_cookie_resumes_mid_episode(
    client: TestClient, db: Database
) -> None:
    participant, session_id = teaching_participant(client)
    teacher, state = start_demonstration(participant, session_id, 3)
    browser = TestClient(client.app)  # a new browser: no cookie; MTurk opens the same link
    arrival = arrive(browser)
    assert arrival.status_code == 200 and arrival.json()["resumed"]
    state_now = arrival.json()["participant"]
    assert state_now["current_session_id"] == session_id
    resumed = Participant(browser, arrival.json()["token"], state_now["next_seq"])
    view = resumed.get(resumed.session(session_id))
    assert view["teaching"]["episode"]["actions"] == 3
    ended = finish_demonstration(resumed, session_id, teacher, state)
    assert ended["outcome"]["episode_ended"] == "goal"
    # The old browser keeps its own token: it reads the same participant, and its next request
    # learns the sequence moved on (409) instead of acting twice.
    assert participant.get("/api/participant")["participant_id"] == state_now["participant_id"]
    assert participant.post(f"{participant.session(session_id)}/reset").status_code == 409


def test_after_a_restart_the_participant_and_the_learner_continue(
    db: Database, settings: Settings, study: StudyConfig, executor: ProcessPoolExecutor
) -> None:
    with TestClient(create_app(settings, study, db=db, executor=executor)) as client:
        participant, session_id = teaching_participant(client)
        teacher, state = start_demonstration(participant, session_id, 2)
        finish_demonstration(participant, session_id, teacher, state)
        wait_for_updates(db)
        teacher, state = start_demonstration(participant, session_id, 2)
        token, seq = participant.token, participant.seq
    # A new server process on the same database (its policy cache is empty).
    with TestClient(create_app(settings, study, db=db, executor=executor)) as client:
        participant = Participant(client, token, seq)
        assert participant.get("/api/participant")["next_seq"] == seq
        view = participant.get(participant.session(session_id))
        assert view["teaching"]["agent"]["state"] == state
        assert view["teaching"]["episode"]["actions"] == 2
        finish_demonstration(participant, session_id, teacher, state)
        wait_for_updates(db)
        base = participant.session(session_id)
        participant.act(f"{base}/reset")
        participant.act(f"{base}/mode", mode="agent")
        step = participant.act(f"{base}/agent-step")
    with db.read() as s:
        latest = s.scalars(
            select(LearnerUpdate)
            .where(LearnerUpdate.session_id == session_id)
            .order_by(LearnerUpdate.update_index.desc())
        ).first()
    assert latest.update_index == 2 and latest.status == "done"
    env = make(view["summary"]["environment"])
    policy = np.frombuffer(latest.greedy_policy, dtype=np.int8).reshape(
        len(env.tasks), env.num_states
    )
    assert ACTIONS.index(step["outcome"]["action"]) == policy[0, step["outcome"]["state"]]
