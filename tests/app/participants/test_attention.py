"""Instructional attention checks between agents: the server moves the robot and decides from
the moves it received (the star reached within the moves allowed: passed; the moves run out:
failed), the participant always goes on to the next agent, a retried move counts once, a reload
shows the check as it was, bad input changes nothing, and an erasure removes the checks."""

from __future__ import annotations

import random
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from server.app.participants.assignment import draw_check_cells
from server.app.rights.erasure import erase_participant
from server.app.storage.db import Database
from server.app.storage.models import AttentionCheck, Event
from server.app.study_file import AttentionChecks, StudyConfig, StudyConfigError
from tests.support.server import (
    Participant,
    demonstrate_each_task,
    study_config,
    teaching_participant,
)

MOVE = "/api/participant/attention-check/move"
# Two agents (one environment, no tutorial): one check between them, robot bottom-left, star
# top-right, eight moves apart.
TWO_AGENTS: dict[str, Any] = {
    "learners": ["cloning"],
    "agents_per_environment": 2,
    "domains": [{"name": "navigation", "environments": ["wall"]}],
    "tutorial": {"enabled": False},
}
CHECKS = {"enabled": True, "size": 5, "start": [4, 0], "star": [0, 4], "moves": 10}
SHORTEST = ["UP"] * 4 + ["RIGHT"] * 4


@pytest.fixture
def study() -> StudyConfig:
    return study_config(**TWO_AGENTS, attention_checks=CHECKS)


def finish_first_agent(client: TestClient) -> tuple[Participant, int]:
    """A participant who taught the first agent and finished it; the second agent's id."""
    participant, first = teaching_participant(client)
    demonstrate_each_task(participant, first)
    done = participant.act(f"/api/sessions/{first}/finish")
    assert done["participant"]["current_session_id"] is None  # the check comes first
    second = participant.get("/api/participant")["sessions"][1]["session_id"]
    return participant, second


def stored_checks(db: Database) -> list[AttentionCheck]:
    with db.read() as s:
        return list(s.scalars(select(AttentionCheck).order_by(AttentionCheck.id)))


def check_events(db: Database) -> list[Event]:
    with db.read() as s:
        return list(
            s.scalars(select(Event).where(Event.kind == "attention_move").order_by(Event.seq))
        )


def test_the_star_reached_within_the_moves_passes_and_the_next_agent_begins(
    client: TestClient, db: Database
) -> None:
    participant, second = finish_first_agent(client)
    check = participant.get("/api/participant")["attention_check"]
    assert check == {
        "number": 1,
        "of": 1,
        "size": 5,
        "robot": [4, 0],
        "star": [0, 4],
        "moves_made": 0,
        "moves_allowed": 10,
        "status": "active",
    }
    for action in SHORTEST[:-1]:
        answer = participant.act(MOVE, action=action)
        assert answer["check"]["status"] == "active"
        assert answer["participant"]["current_session_id"] is None
    answer = participant.act(MOVE, action=SHORTEST[-1])
    assert answer["check"]["status"] == "passed" and answer["check"]["robot"] == [0, 4]
    assert answer["participant"]["current_session_id"] == second
    me = participant.get("/api/participant")
    assert me["attention_check"] is None and me["current_session_id"] == second
    (row,) = stored_checks(db)
    assert (row.status, row.moves, row.cell) == ("passed", SHORTEST, 4)
    assert row.started_at is not None and row.finished_at is not None
    events = check_events(db)
    assert [(e.state, e.next_state) for e in events[:2]] == [(20, 15), (15, 10)]
    assert len(events) == len(SHORTEST) and all(e.session_id is None for e in events)
    # The check is over: another move is refused.
    assert participant.post(MOVE, action="UP").status_code == 409


def test_moves_running_out_fail_the_check_and_the_participant_goes_on(
    client: TestClient, db: Database
) -> None:
    participant, second = finish_first_agent(client)
    # Into the edge: the robot stays, each move counts.
    for _ in range(9):
        answer = participant.act(MOVE, action="LEFT")
        assert answer["check"]["status"] == "active" and answer["check"]["robot"] == [4, 0]
    assert answer["check"]["moves_made"] == 9
    answer = participant.act(MOVE, action="DOWN")
    assert answer["check"]["status"] == "failed" and answer["check"]["moves_made"] == 10
    assert answer["participant"]["current_session_id"] == second
    (row,) = stored_checks(db)
    assert row.status == "failed" and row.moves == ["LEFT"] * 9 + ["DOWN"]
    assert len(check_events(db)) == 10
    # The next agent is taught as usual.
    demonstrate_each_task(participant, second)
    done = participant.act(f"/api/sessions/{second}/finish")
    assert done["participant"]["status"] == "completed"


def test_a_reload_mid_check_shows_it_as_it_was(client: TestClient, db: Database) -> None:
    participant, second = finish_first_agent(client)
    participant.act(MOVE, action="UP")
    participant.act(MOVE, action="RIGHT")
    participant.act(MOVE, action="DOWN")
    # The reloaded page knows only the cookie.
    me = client.get("/api/participant").json()
    assert me["status"] == "teaching" and me["current_session_id"] is None
    check = me["attention_check"]
    assert (check["robot"], check["moves_made"], check["status"]) == ([4, 1], 3, "active")
    # The next agent waits for the check.
    assert client.get(f"/api/sessions/{second}").json()["summary"]["status"] == "pending"
    resumed = Participant(client, participant.token, me["next_seq"])
    refused = resumed.post(f"/api/sessions/{second}/move", action="UP")
    assert refused.status_code == 409
    for action in ["UP"] * 4 + ["RIGHT"] * 2:
        answer = resumed.act(MOVE, action=action)
        assert answer["check"]["status"] == "active"
    # The star on the last move allowed: passed.
    answer = resumed.act(MOVE, action="RIGHT")
    assert answer["check"]["status"] == "passed" and answer["check"]["moves_made"] == 10
    assert answer["participant"]["current_session_id"] == second


def test_a_retried_move_counts_once(client: TestClient, db: Database) -> None:
    participant, _ = finish_first_agent(client)
    first = participant.post(MOVE, action="UP")
    again = participant.post(MOVE, action="UP")
    assert first.status_code == again.status_code == 200
    assert first.json() == again.json()
    # The same seq for another move is refused.
    assert participant.post(MOVE, action="RIGHT").status_code == 409
    (row,) = stored_checks(db)
    assert row.moves == ["UP"] and row.cell == 15
    assert len(check_events(db)) == 1


@pytest.mark.parametrize(
    "body",
    [
        {"action": "STAY"},
        {"action": "up"},
        {"action": 1},
        {},
        {"action": "UP", "extra": 1},
    ],
)
def test_bad_moves_are_refused_and_change_nothing(
    client: TestClient, db: Database, body: dict[str, Any]
) -> None:
    participant, _ = finish_first_agent(client)
    participant.act(MOVE, action="UP")
    before = participant.get("/api/participant")
    response = participant.post(MOVE, **body)
    assert response.status_code == 422, response.text
    no_seq = client.post(MOVE, json={"action": "UP"}, headers=participant.headers)
    assert no_seq.status_code == 422
    assert participant.get("/api/participant") == before
    (row,) = stored_checks(db)
    assert row.moves == ["UP"] and row.status == "active"


def test_a_move_with_no_check_in_progress_is_refused(client: TestClient, db: Database) -> None:
    participant, _ = teaching_participant(client)
    response = participant.post(MOVE, action="UP")
    assert response.status_code == 409
    assert "no attention check" in response.json()["detail"]
    assert participant.get("/api/participant")["next_seq"] == participant.seq
    assert all(row.status == "pending" and row.moves == [] for row in stored_checks(db))


def test_a_study_without_checks_goes_from_agent_to_agent(db: Database, executor: Any) -> None:
    from server.app.main import create_app
    from tests.support.server import make_settings

    study = study_config(**TWO_AGENTS)
    assert not study.attention_checks.enabled
    settings = make_settings(db.engine.url.render_as_string(hide_password=False))
    with TestClient(create_app(settings, study, db=db, executor=executor)) as client:
        participant, first = teaching_participant(client)
        demonstrate_each_task(participant, first)
        done = participant.act(f"/api/sessions/{first}/finish")
        assert done["participant"]["current_session_id"] is not None
        assert participant.get("/api/participant")["attention_check"] is None
        assert participant.post(MOVE, action="UP").status_code == 409
    assert stored_checks(db) == []


def test_checks_come_after_every_kth_agent_but_never_after_the_last(
    client: TestClient, db: Database
) -> None:
    checks = AttentionChecks(enabled=True, every=2)
    assert checks.after_agents(6) == [1, 3]
    assert AttentionChecks(enabled=True).after_agents(3) == [0, 1]
    assert AttentionChecks(enabled=True, every=3).after_agents(3) == []
    assert AttentionChecks().after_agents(6) == []
    # Consent made this study's one check, after the first agent (ordinal 0).
    teaching_participant(client)
    (row,) = stored_checks(db)
    assert (row.number, row.after_ordinal, row.status) == (0, 0, "pending")


def test_random_cells_are_drawn_from_the_seed_far_enough_apart() -> None:
    checks = AttentionChecks(enabled=True, start="random", star="random", moves=8)
    pairs = [draw_check_cells(checks, random.Random(seed)) for seed in range(200)]
    assert pairs == [draw_check_cells(checks, random.Random(seed)) for seed in range(200)]
    for start, star in pairs:
        (r0, c0), (r1, c1) = divmod(start, 5), divmod(star, 5)
        assert abs(r0 - r1) + abs(c0 - c1) >= 4
    assert len(set(pairs)) > 20
    fixed_star = AttentionChecks(enabled=True, start="random", star=(2, 2), moves=8)
    for seed in range(50):
        start, star = draw_check_cells(fixed_star, random.Random(seed))
        assert star == 12 and start in {0, 4, 20, 24}  # the corners: four moves from the centre


@pytest.mark.parametrize(
    ("table", "problem"),
    [
        ({"start": [5, 0]}, "off the 5x5 grid"),
        ({"star": [4, 0]}, "the same cell"),
        ({"moves": 7}, "less than the 8"),
        ({"start": "random", "moves": 7}, "less than the 8"),
        ({"size": 2}, "greater than or equal to 3"),
        ({"every": 0}, "greater than or equal to 1"),
        ({"start": "centre"}, "attention_checks.start"),
        ({"start": [True, 0]}, "two whole numbers"),
        ({"star": [0.0, 4]}, "two whole numbers"),
        ({"star": [0, 4, 1]}, "two whole numbers"),
        ({"moves": "12"}, "attention_checks.moves"),
        ({"enabled": 1}, "attention_checks.enabled"),
        ({"colour": "red"}, "colour"),
    ],
)
def test_a_bad_attention_checks_table_is_refused(table: dict[str, Any], problem: str) -> None:
    with pytest.raises(StudyConfigError, match=problem):
        study_config(attention_checks={"enabled": True, **table})


def test_checks_that_would_never_come_are_refused() -> None:
    # Two agents: a check every second agent would come after the last one only.
    with pytest.raises(StudyConfigError, match="every = 2 leaves no check"):
        study_config(**TWO_AGENTS, attention_checks={**CHECKS, "every": 2})
    assert study_config(**TWO_AGENTS, attention_checks={**CHECKS, "every": 1})


def test_an_erasure_removes_the_participants_checks_and_no_other(
    client: TestClient, db: Database
) -> None:
    first, _ = finish_first_agent(client)
    first.act(MOVE, action="UP")
    client.cookies.clear()
    teaching_participant(client, worker="W2", assignment="A2")
    checks = stored_checks(db)
    assert len(checks) == 2
    mine, other = checks
    erased = erase_participant(db, mine.participant_id, "experimenter")
    assert erased.rows["attention_checks"] == 1
    assert [row.id for row in stored_checks(db)] == [other.id]
    with db.read() as s:
        left = s.scalar(
            select(func.count()).select_from(Event).where(Event.kind == "attention_move")
        )
    assert left == 0
