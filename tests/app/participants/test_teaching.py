"""The teaching API of one learning session: every route, what it records, and every bad input
answered with a 4xx that changes nothing."""

from __future__ import annotations

from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from server import learners
from server.app.storage.db import Database
from server.app.storage.models import Episode, Event, LearnerUpdate, LearningSession
from server.domains import make
from server.domains.base import ACTIONS, STAY
from tests.app.updates.test_updates import demonstrate
from tests.support.server import (
    Participant,
    count_events,
    demonstrate_each_task,
    teaching_participant,
    wait_for_updates,
)


def snapshot(db: Database) -> tuple[Any, ...]:
    """Everything a request could change."""
    with db.read() as s:
        sessions = [
            (
                x.id,
                x.status,
                x.task,
                x.mode,
                x.state,
                x.open_episode,
                x.episodes,
                x.actions,
                tuple(x.demonstrated),
                x.updates_requested,
                x.last_action,
            )
            for x in s.scalars(select(LearningSession).order_by(LearningSession.id))
        ]
        updates = len(s.scalars(select(LearnerUpdate)).all())
        episodes = len(s.scalars(select(Episode)).all())
    return count_events(db), tuple(sessions), updates, episodes


def first_study_session(participant: Participant, tutorial: int) -> int:
    demonstrate_each_task(participant, tutorial)
    data = participant.act(f"/api/sessions/{tutorial}/finish")
    return data["participant"]["current_session_id"]


def test_a_demonstration_reaching_the_goal_ends_with_a_synthetic_stay(
    client: TestClient, db: Database
) -> None:
    participant, session_id = teaching_participant(client)
    base = participant.session(session_id)
    view = participant.get(base)
    env = make(view["summary"]["environment"])
    from server.teacher import Teacher

    teacher = Teacher(env, seed=0)
    state = view["teaching"]["agent"]["state"]
    assert view["teaching"]["mode"] == "idle" and view["teaching"]["task"] == 0
    participant.act(f"{base}/mode", mode="demonstrate")
    moves = 0
    while True:
        data = participant.act(f"{base}/move", action=ACTIONS[teacher.next_action(0, state)])
        moves += 1
        assert data["outcome"]["state"] == state
        state = data["session"]["agent"]["state"]
        if data["outcome"]["episode_ended"]:
            break
        assert data["session"]["episode"] == {
            "index": 0,
            "kind": "demonstration",
            "task": 0,
            "actions": moves,
        }
    assert data["outcome"]["goal_reached"] and data["outcome"]["episode_ended"] == "goal"
    assert data["outcome"]["update_queued"] == 1
    teaching = data["session"]
    assert teaching["mode"] == "idle" and teaching["episode"] is None
    assert teaching["episodes"] == 1 and teaching["actions"] == moves
    assert teaching["demonstrated"][0] == moves
    with db.read() as s:
        last = s.scalars(select(Event).order_by(Event.id.desc())).first()
        assert last.record == "demonstration" and last.episode_end == "goal"
        assert last.stay_state == env.step(last.next_state, STAY, None)  # STAY stays
        episode = s.scalars(select(Episode)).one()
        assert (episode.kind, episode.actions, episode.end_reason, episode.update_index) == (
            "demonstration",
            moves,
            "goal",
            1,
        )
        update = s.scalars(select(LearnerUpdate).where(LearnerUpdate.update_index == 1)).one()
        assert (update.episodes, update.actions, update.through_event_id) == (1, moves, last.id)


def test_a_demonstration_ended_by_the_participant_gets_a_synthetic_stay(
    client: TestClient, db: Database
) -> None:
    participant, session_id = teaching_participant(client)
    base = participant.session(session_id)
    env = make(participant.get(base)["summary"]["environment"])
    # One demonstrated move that does not reach the goal (start again if it did: an episode
    # that reaches the goal leaves the mode idle, so demonstrating is chosen on every try).
    demonstrated = 0  # moves demonstrated, in this try and in those that reached the goal
    for _ in range(20):
        start = participant.act(f"{base}/reset")["session"]["agent"]["state"]
        if env.is_goal(0, start):
            continue
        participant.act(f"{base}/mode", mode="demonstrate")
        moved = participant.act(f"{base}/move", action="UP")
        demonstrated += 1
        if not moved["outcome"]["episode_ended"]:
            break
    else:
        pytest.fail("every move reached the goal")
    assert moved["session"]["mode"] == "demonstrate"
    state, at = moved["outcome"]["state"], moved["session"]["agent"]["state"]
    ended = participant.act(f"{base}/end-episode")
    assert ended["outcome"]["episode_ended"] == "end" and not ended["outcome"]["goal_reached"]
    assert ended["session"]["mode"] == "idle" and ended["session"]["episode"] is None
    stay_state = env.step(at, STAY, None)
    assert ended["session"]["agent"]["state"] == stay_state
    # The STAY is the learner's, not a demonstrated move.
    assert ended["session"]["actions"] == demonstrated
    with db.read() as s:
        last = s.scalars(select(Event).order_by(Event.id.desc())).first()
        assert (last.kind, last.record, last.episode_end) == ("end_episode", None, "end")
        assert (last.task, last.next_state, last.stay_state) == (0, at, stay_state)
        episode = s.scalars(
            select(Episode).where(Episode.session_id == session_id).order_by(Episode.id.desc())
        ).first()
        assert (episode.kind, episode.end_reason, episode.actions) == ("demonstration", "end", 1)
    # The learner's data: the demonstrated move, then the STAY where the participant stopped.
    update_index = ended["outcome"]["update_queued"]
    wait_for_updates(db)
    with db.read() as s:
        saved = s.scalars(
            select(LearnerUpdate.learner_state).where(
                LearnerUpdate.session_id == session_id,
                LearnerUpdate.update_index == update_index,
            )
        ).one()
    learner = learners.restore(env, learners.loads(saved))
    assert learner.data.demonstrations.tolist()[-2:] == [
        [0, state, ACTIONS.index("UP"), at],
        [0, at, STAY, stay_state],
    ]


def test_a_move_while_the_agent_tries_is_refused_and_stores_nothing(
    client: TestClient, db: Database
) -> None:
    participant, session_id = teaching_participant(client)
    base = participant.session(session_id)
    participant.act(f"{base}/mode", mode="agent")
    participant.act(f"{base}/agent-step")
    before = snapshot(db)
    for action in ("UP", "LEFT"):
        response = participant.post(f"{base}/move", action=action)
        assert response.status_code == 409, response.text
        assert "the agent is acting on its own: stop it before moving it" in response.text
    assert snapshot(db) == before
    # The refused request used up no sequence number: the same seq is free for the next one.
    assert participant.get("/api/participant")["next_seq"] == participant.seq
    stopped = participant.act(f"{base}/mode", mode="idle")
    assert stopped["outcome"]["episode_ended"] == "mode"
    assert participant.act(f"{base}/move", action="UP")["session"]["mode"] == "idle"


def test_idle_moves_agent_steps_feedback_reset_and_task_switches(
    client: TestClient, db: Database
) -> None:
    participant, tutorial = teaching_participant(client)
    session_id = first_study_session(participant, tutorial)
    base = participant.session(session_id)
    view = participant.get(base)
    assert view["summary"]["kind"] == "study" and view["summary"]["position"] == 0
    assert view["teaching"]["can_finish"] is False
    assert "not yet" in view["teaching"]["finish_blocked"]
    # Idle: the agent moves, nothing is demonstrated, the transition is recorded.
    idle = participant.act(f"{base}/move", action="UP")
    assert (
        idle["session"]["episode"] is None
        and idle["session"]["demonstrated"] == view["teaching"]["demonstrated"]
    )
    # Demonstrate one move, then switch task: the episode ends without a STAY and updates.
    participant.act(f"{base}/mode", mode="demonstrate")
    participant.act(f"{base}/move", action="DOWN")
    switched = participant.act(f"{base}/task", task=1)
    assert (
        switched["outcome"]["episode_ended"] == "task" and switched["outcome"]["update_queued"] == 1
    )
    assert switched["session"]["task"] == 1 and switched["session"]["mode"] == "demonstrate"
    # Reset ends an open episode too and draws a start of the selected task.
    participant.act(f"{base}/move", action="LEFT")
    reset = participant.act(f"{base}/reset")
    assert reset["outcome"]["episode_ended"] == "reset" and reset["outcome"]["update_queued"] == 2
    # Let the agent try: it acts on its greedy policy; feedback on its latest action.
    participant.act(f"{base}/mode", mode="agent")
    step = participant.act(f"{base}/agent-step")
    assert step["outcome"]["action"] in ACTIONS
    assert step["session"]["can_give_feedback"] is True
    feedback = participant.act(f"{base}/feedback", feedback=-1)
    assert feedback["outcome"]["feedback"] == -1
    # Stop: the agent episode ends (no STAY for agent episodes) and updates.
    stop = participant.act(f"{base}/end-episode")
    assert stop["outcome"]["episode_ended"] == "end" and stop["session"]["mode"] == "idle"
    wait_for_updates(db)
    with db.read() as s:
        events = s.scalars(
            select(Event).where(Event.session_id == session_id).order_by(Event.id)
        ).all()
        records = [(e.kind, e.record, e.episode_end, e.stay_state) for e in events]
    assert records == [
        ("move", "transition", None, None),
        ("mode", None, None, None),
        ("move", "demonstration", None, None),
        ("task", None, "task", None),
        ("move", "demonstration", None, None),
        ("reset", None, "reset", None),
        ("mode", None, None, None),
        ("agent_step", "agent_step", None, None),
        ("feedback", "feedback", None, None),
        ("end_episode", None, "end", None),
    ]
    learning = participant.get(f"{base}/learning")
    assert learning == {"pending": 0, "updates": 3}  # three episodes ended; update 0 is not counted


def test_the_agent_episode_ends_at_the_horizon(client: TestClient, db: Database) -> None:
    participant, session_id = teaching_participant(client)
    base = participant.session(session_id)
    env = make(participant.get(base)["summary"]["environment"])
    participant.act(f"{base}/mode", mode="agent")
    # The untrained agent does not reach the goal: it acts until the horizon.
    for step in range(env.horizon):  # noqa: B007 (used after the loop)
        data = participant.act(f"{base}/agent-step")
        if data["outcome"]["episode_ended"]:
            break
    assert data["outcome"]["episode_ended"] in ("horizon", "goal")
    if data["outcome"]["episode_ended"] == "horizon":
        assert step == env.horizon - 1
    assert data["session"]["mode"] == "idle"
    assert participant.post(f"{base}/agent-step").status_code == 409


def test_bad_requests_get_clear_4xx_and_change_nothing(client: TestClient, db: Database) -> None:
    participant, tutorial = teaching_participant(client)
    other, other_session = teaching_participant(TestClient(client.app), "W2", "A2")
    base = participant.session(tutorial)
    with db.read() as s:
        pending_session = s.scalars(
            select(LearningSession.id).where(
                LearningSession.participant_id == 1, LearningSession.status == "pending"
            )
        ).first()
    before = snapshot(db)
    cases: list[tuple[str, Any, int, str]] = [
        (f"{base}/move", {"seq": participant.seq, "action": "STAY"}, 422, "UP"),
        (f"{base}/move", {"seq": participant.seq, "action": "JUMP"}, 422, "UP"),
        (f"{base}/move", {"seq": participant.seq}, 422, "action"),
        (f"{base}/move", {"action": "UP"}, 422, "seq"),
        (f"{base}/move", {"seq": 0, "action": "UP"}, 422, "seq"),
        (f"{base}/move", {"seq": participant.seq, "action": "UP", "extra": 1}, 422, "extra"),
        (f"{base}/task", {"seq": participant.seq, "task": 99}, 400, "does not exist"),
        (f"{base}/task", {"seq": participant.seq, "task": -1}, 422, "task"),
        (f"{base}/task", {"seq": participant.seq, "task": "one"}, 422, "task"),
        (f"{base}/mode", {"seq": participant.seq, "mode": "fly"}, 422, "mode"),
        (f"{base}/feedback", {"seq": participant.seq, "feedback": 2}, 422, "feedback"),
        (f"{base}/feedback", {"seq": participant.seq, "feedback": 1}, 409, "no agent action"),
        (f"{base}/agent-step", {"seq": participant.seq}, 409, "mode agent"),
        (f"{base}/end-episode", {"seq": participant.seq}, 409, "no episode"),
        (
            f"/api/sessions/{other_session}/move",
            {"seq": participant.seq, "action": "UP"},
            404,
            "no learning session",
        ),
        (
            "/api/sessions/999999/move",
            {"seq": participant.seq, "action": "UP"},
            404,
            "no learning session",
        ),
        (
            f"/api/sessions/{pending_session}/move",
            {"seq": participant.seq, "action": "UP"},
            409,
            "not come yet",
        ),
        ("/api/sessions/abc/move", {"seq": participant.seq, "action": "UP"}, 422, "session_id"),
        (f"{base}/move", {"seq": participant.seq + 1, "action": "UP"}, 409, "out of order"),
        (
            "/api/participant/consent",
            {"seq": participant.seq, "agree": True},
            409,
            "already answered",
        ),
        ("/api/participant/start", {"seq": participant.seq}, 409, "cannot start"),
        ("/api/participant/submission", {"seq": participant.seq}, 409, "not completed"),
    ]
    for path, body, status, words in cases:
        response = client.post(path, json=body, headers=participant.headers)
        assert response.status_code == status, (path, body, response.text)
        assert words in response.text, (path, body, response.text)
    # Not JSON, too large, no token, a wrong token, another participant's session to read.
    assert (
        client.post(
            f"{base}/move",
            content=b"UP",
            headers={**participant.headers, "content-type": "application/json"},
        ).status_code
        == 422
    )
    huge = client.post(
        f"{base}/move",
        content=b'{"seq": 1, "action": "UP", "note": "' + b"x" * 10_000 + b'"}',
        headers={**participant.headers, "content-type": "application/json"},
    )
    assert huge.status_code == 413 and "too large" in huge.text

    def chunks():
        for _ in range(10):
            yield b" " * 1000

    streamed = client.post(
        f"{base}/move",
        content=chunks(),
        headers={**participant.headers, "content-type": "application/json"},
    )
    assert streamed.status_code == 413
    anonymous = TestClient(client.app)
    assert (
        anonymous.post(f"{base}/move", json={"seq": participant.seq, "action": "UP"}).status_code
        == 401
    )
    forged = anonymous.post(
        f"{base}/move",
        json={"seq": participant.seq, "action": "UP"},
        headers={"X-Participant-Token": "forged"},
    )
    assert forged.status_code == 401 and "unknown participant" in forged.text
    assert (
        client.get(f"/api/sessions/{other_session}", headers=participant.headers).status_code == 404
    )
    assert client.get(f"/api/sessions/{tutorial}", headers=other.headers).status_code == 404
    assert (
        client.get(f"/api/sessions/{tutorial}/learning", headers=other.headers).status_code == 404
    )
    assert anonymous.get("/api/participant").status_code == 401
    assert snapshot(db) == before
    assert participant.get("/api/participant")["next_seq"] == participant.seq


def test_finishing_is_refused_until_every_task_has_a_demonstration(
    client: TestClient, db: Database
) -> None:
    participant, tutorial = teaching_participant(client)
    session_id = first_study_session(participant, tutorial)
    base = participant.session(session_id)
    view = participant.get(base)
    tasks = [t["name"] for t in view["environment"]["tasks"]]
    participant.act(f"{base}/mode", mode="demonstrate")
    participant.act(f"{base}/move", action="UP")
    refused = participant.post(f"{base}/finish")
    assert refused.status_code == 409
    assert ", ".join(tasks[1:]) in refused.json()["detail"]
    demonstrate_each_task(participant, session_id)
    finished = participant.act(f"{base}/finish")
    assert finished["session"]["status"] == "finished"
    following = finished["participant"]["current_session_id"]
    assert following != session_id
    assert participant.post(f"{base}/move", action="UP").status_code == 409  # finished agent
    assert participant.get(participant.session(following))["summary"]["position"] == 1


@pytest.mark.parametrize("mode", ["demonstrate", "idle"])
def test_moves_follow_the_true_dynamics(client: TestClient, db: Database, mode: str) -> None:
    participant, session_id = teaching_participant(client)
    base = participant.session(session_id)
    env = make(participant.get(base)["summary"]["environment"])
    participant.act(f"{base}/mode", mode=mode)
    for name in ["UP", "LEFT", "LEFT", "DOWN", "RIGHT"]:
        data = participant.act(f"{base}/move", action=name)
        outcome = data["outcome"]
        probabilities = env.transition_probabilities()[outcome["state"], ACTIONS.index(name)]
        assert probabilities[outcome["next_state"]] > 0
        if data["outcome"]["episode_ended"]:
            break


def demonstrate_to_goal(participant: Participant, base: str, task: int) -> int:
    """A demonstration of ``task`` by the simulated teacher, to its goal: the goal's state."""
    participant.act(f"{base}/mode", mode="idle")
    data = demonstrate(participant, int(base.rsplit("/", 1)[1]), task)
    assert data["outcome"]["episode_ended"] == "goal"
    return int(data["session"]["agent"]["state"])


def counts(db: Database, session_id: int) -> tuple[int, int, int]:
    """(episodes, episode rows, learner updates queued) of the session."""
    with db.read() as s:
        session = s.get(LearningSession, session_id)
        rows = s.scalars(select(Episode).where(Episode.session_id == session_id)).all()
        updates = s.scalars(
            select(LearnerUpdate).where(LearnerUpdate.session_id == session_id)
        ).all()
        return session.episodes, len(rows), len(updates)


def test_a_try_from_the_goal_starts_a_real_episode_from_a_random_start(
    client: TestClient, db: Database
) -> None:
    """The issue's sequence: a demonstration reaches the goal, then T, T, T. Turning the agent on
    at the goal records no episode and queues no update: the agent is put at a random start
    first, and its try from there is the next episode, which does not start on the goal."""
    participant, session_id = teaching_participant(client)
    base = participant.session(session_id)
    env = make(participant.get(base)["summary"]["environment"])
    for _ in range(3):
        goal = demonstrate_to_goal(participant, base, 0)
        assert env.is_goal(0, goal)
        before = counts(db, session_id)
        tried = participant.act(f"{base}/mode", mode="agent")
        outcome = tried["outcome"]
        assert outcome["new_start"] is True and outcome["episode_ended"] is None
        assert outcome["state"] == goal and not env.is_goal(0, outcome["next_state"])
        assert tried["session"]["agent"]["state"] == outcome["next_state"]
        assert tried["session"]["can_give_feedback"] is False
        assert counts(db, session_id) == before  # no episode, no update
        start = outcome["next_state"]
        wait_for_updates(db)
        step = participant.act(f"{base}/agent-step")
        assert step["outcome"]["state"] == start
        with db.read() as s:
            episode = s.scalars(
                select(Episode)
                .where(Episode.session_id == session_id)
                .order_by(Episode.index.desc())
            ).first()
            assert (episode.kind, episode.start_state) == ("agent", start)
            event = s.scalars(select(Event).where(Event.seq == step["seq"] - 1)).one()
            assert (event.kind, event.state, event.next_state) == ("mode", goal, start)
        if step["session"]["mode"] == "agent":
            participant.act(f"{base}/end-episode")
    # Every episode of the session starts away from its task's goal.
    with db.read() as s:
        episodes = s.scalars(select(Episode).where(Episode.session_id == session_id)).all()
    assert len(episodes) == 6
    assert not [e.index for e in episodes if env.is_goal(e.task, e.start_state)]


def test_demonstrating_or_selecting_a_task_on_its_goal_starts_from_a_random_start(
    client: TestClient, db: Database
) -> None:
    participant, session_id = teaching_participant(client)
    base = participant.session(session_id)
    env = make(participant.get(base)["summary"]["environment"])
    # Demonstrate (D) on the goal: a random start first, no episode.
    goal = demonstrate_to_goal(participant, base, 0)
    before = counts(db, session_id)
    shown = participant.act(f"{base}/mode", mode="demonstrate")
    assert shown["outcome"]["new_start"] and shown["outcome"]["state"] == goal
    start = shown["session"]["agent"]["state"]
    assert not env.is_goal(0, start) and counts(db, session_id) == before
    # The demonstration's episode starts where its first move starts.
    moved = participant.act(f"{base}/move", action="UP")
    with db.read() as s:
        episode = s.scalars(
            select(Episode).where(Episode.session_id == session_id).order_by(Episode.id.desc())
        ).first()
    assert episode.start_state == moved["outcome"]["state"] == start
    # Selecting a task whose goal the agent stands on, while the agent tries: a random start.
    goal = demonstrate_to_goal(participant, base, 1)
    participant.act(f"{base}/task", task=0)
    participant.act(f"{base}/move", action="UP")  # idle: no episode
    back = participant.act(f"{base}/move", action="DOWN")
    if back["session"]["agent"]["state"] != goal:
        pytest.skip("the goal cannot be left and re-entered with UP and DOWN here")
    participant.act(f"{base}/mode", mode="agent")  # task 0: not on its goal
    before = counts(db, session_id)
    switched = participant.act(f"{base}/task", task=1)
    assert switched["outcome"]["new_start"] and switched["outcome"]["state"] == goal
    assert not env.is_goal(1, switched["session"]["agent"]["state"])
    assert counts(db, session_id) == before
    # Idle, nothing moves the agent off the goal: no episode can begin there.
    goal = demonstrate_to_goal(participant, base, 1)
    idle = participant.act(f"{base}/task", task=1)
    assert idle["outcome"]["new_start"] is False and idle["session"]["agent"]["state"] == goal


@pytest.mark.parametrize("name", ["wall", "three-rooms", "flip", "choices", "navigation-tutorial"])
def test_random_starts_are_never_on_the_task_s_goal(name: str) -> None:
    """These environments' study start distributions include the goals (about 1 in 60 to 1 in
    130 draws): a reset there would be a start with nothing to do."""
    import numpy as np

    from server.app.participants.assignment import random_start

    env = make(name)
    rng = np.random.default_rng(0)
    for task in range(len(env.tasks)):
        starts = {random_start(name, task, rng) for _ in range(1500)}
        assert not [s for s in starts if env.is_goal(task, s)]
        possible = env.tasks[task].study_start_distribution > 0
        assert len(starts) > 0.8 * (possible.sum() - (env.tasks[task].reward > 0).sum())
