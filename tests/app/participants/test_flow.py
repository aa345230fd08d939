"""The participant flow: consent, balanced domains, the order of agents, statuses with
timestamps, completion codes issued only after the completion is committed."""

from __future__ import annotations

import threading
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from datetime import timedelta
from itertools import groupby, pairwise
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select, update

from server.app.participants import assignment, tokens
from server.app.participants.statuses import mark_abandoned
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import LearningSession, StatusChange, utcnow
from server.app.storage.models import Participant as ParticipantRow
from server.app.study_file import StudyConfig
from tests.support.server import (
    ADMIN_TOKEN,
    Participant,
    arrive,
    demonstrate_each_task,
    new_participant,
    teaching_participant,
)


def test_declining_consent_ends_the_flow(client: TestClient, db: Database) -> None:
    participant = new_participant(client)
    data = participant.act("/api/participant/consent", agree=False)
    assert data["participant"]["status"] == "declined"
    state = participant.get("/api/participant")
    assert state["domain"] is None and state["sessions"] == []
    assert participant.post("/api/participant/start").status_code == 409


def test_consent_assigns_a_domain_and_orders_the_agents(client: TestClient, db: Database) -> None:
    participant = new_participant(client)
    participant.act("/api/participant/consent", agree=True)
    state = participant.get("/api/participant")
    assert state["status"] == "consented" and state["domain"] in ("navigation", "farming")
    sessions = state["sessions"]
    assert [s["kind"] for s in sessions] == ["tutorial"] + ["study"] * 6
    assert sessions[0]["environment"] == f"{state['domain']}-tutorial"
    expected = {"navigation": ["two-rooms", "doorway"], "farming": ["two-fields", "three-fields"]}
    assert [s["environment"] for s in sessions[1:]] == [
        e for e in expected[state["domain"]] for _ in range(3)
    ]
    assert [s["position"] for s in sessions[1:]] == list(range(6))
    assert len({s["colour"]["name"] for s in sessions[1:]}) == 6
    assert all("learner" not in s for s in sessions)  # participants are blind to the learner
    with db.read() as s:
        rows = s.scalars(
            select(LearningSession)
            .where(LearningSession.kind == "study")
            .order_by(LearningSession.position)
        ).all()
    for environment in range(2):
        learners = [row.learner for row in rows[3 * environment : 3 * environment + 3]]
        assert sorted(learners) == ["bam", "cloning", "model-based"]
    assert state["progress"] == {"agent": 0, "of": 6}


def test_learner_orders_are_randomised(
    client: TestClient, db: Database, study: StudyConfig
) -> None:
    """Per participant and environment: each environment's agents are the configured learners
    in an order drawn for that environment alone."""
    for index in range(12):
        participant = new_participant(TestClient(client.app), f"W{index}", f"A{index}")
        participant.act("/api/participant/consent", agree=True)
    orders: dict[int, list[tuple[str, ...]]] = {}
    with db.read() as s:
        rows = s.scalars(
            select(LearningSession)
            .where(LearningSession.kind == "study")
            .order_by(LearningSession.participant_id, LearningSession.position)
        ).all()
    for participant_id, sessions in groupby(rows, key=lambda row: row.participant_id):
        by_environment: dict[str, list[str]] = {}
        for row in sessions:
            by_environment.setdefault(row.environment, []).append(row.learner)
        orders[participant_id] = [tuple(learners) for learners in by_environment.values()]
    assert len(orders) == 12
    for first, second in orders.values():
        assert sorted(first) == sorted(second) == sorted(study.learners)
    # Not one order for everybody, and not one order per participant for both environments.
    # (By chance the last fails about once in 6**12 runs.)
    assert len({order for both in orders.values() for order in both}) > 1
    assert any(first != second for first, second in orders.values())


def test_simultaneous_consents_are_balanced(
    client: TestClient, db: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Participants who consent at the same moment each count the others' domains: the
    domains differ by at most one. To make a race show every time, ties go to the first domain
    and each consent waits between choosing its domain and committing."""
    participants = [
        new_participant(TestClient(client.app), f"W{index}", f"A{index}") for index in range(8)
    ]
    create_sessions = assignment.create_sessions

    def slow_create_sessions(*args: Any) -> None:
        time.sleep(0.1)
        create_sessions(*args)

    monkeypatch.setattr(assignment, "create_sessions", slow_create_sessions)
    monkeypatch.setattr(tokens.SYSTEM_RANDOM, "choice", lambda names: names[0])
    ready = threading.Barrier(len(participants))

    def consent(participant: Participant) -> str:
        ready.wait()
        participant.act("/api/participant/consent", agree=True)
        return str(participant.get("/api/participant")["domain"])

    with ThreadPoolExecutor(len(participants)) as pool:
        counts = Counter(pool.map(consent, participants))
    assert set(counts) == {"navigation", "farming"}
    assert max(counts.values()) - min(counts.values()) <= 1, counts


def test_domain_assignment_holds_its_lock_until_the_transaction_ends(db: Database) -> None:
    if db.is_sqlite:
        # Only a write transaction (BEGIN IMMEDIATE) keeps other writers out while counting.
        with db.connect() as c, pytest.raises(RuntimeError, match="write transaction"):
            assignment.lock_domain_assignment(c)
        with db.transaction() as c:
            assignment.lock_domain_assignment(c)
        return
    try_lock = select(func.pg_try_advisory_xact_lock(assignment.DOMAIN_LOCK_KEY))
    with db.transaction() as c:
        assignment.lock_domain_assignment(c)
        with db.transaction() as other:
            assert other.scalar(try_lock) is False
    with db.transaction() as other:
        assert other.scalar(try_lock) is True


def test_domains_are_balanced_counting_only_active_and_completed(
    client: TestClient, db: Database
) -> None:
    domains = []
    for index in range(8):
        participant = new_participant(TestClient(client.app), f"W{index}", f"A{index}")
        participant.act("/api/participant/consent", agree=True)
        domains.append(participant.get("/api/participant")["domain"])
    assert Counter(domains) == {"navigation": 4, "farming": 4}
    # The navigation participants go idle: they no longer hold places, so navigation is the
    # least filled domain and the next arrivals go there.
    with db.write() as s:
        s.execute(
            update(ParticipantRow)
            .where(ParticipantRow.domain == "navigation")
            .values(last_seen_at=utcnow() - timedelta(hours=1))
        )
    following = []
    for index in range(8, 12):
        participant = new_participant(TestClient(client.app), f"W{index}", f"A{index}")
        participant.act("/api/participant/consent", agree=True)
        following.append(participant.get("/api/participant")["domain"])
    assert following == ["navigation"] * 4
    # Excluded participants do not count either.
    admin = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
    with db.read() as s:
        farming = s.scalars(
            select(ParticipantRow.id).where(ParticipantRow.domain == "farming")
        ).all()
    for participant_id in farming:
        assert (
            client.post(
                f"/api/admin/participants/{participant_id}/exclusion",
                json={"reason": "test"},
                headers=admin,
            ).status_code
            == 200
        )
    participant = new_participant(TestClient(client.app), "W99", "A99")
    participant.act("/api/participant/consent", agree=True)
    assert participant.get("/api/participant")["domain"] == "farming"


def test_idle_participants_are_marked_abandoned_and_continue_if_they_return(
    client: TestClient, db: Database, settings: Settings
) -> None:
    participant, session_id = teaching_participant(client)
    with db.write() as s:
        s.execute(update(ParticipantRow).values(last_seen_at=utcnow() - timedelta(hours=5)))
    assert mark_abandoned(db, settings) == 1
    assert participant.get("/api/participant")["status"] == "abandoned"
    data = participant.act(f"{participant.session(session_id)}/move", action="UP")
    assert data["participant"]["status"] == "tutorial"
    with db.read() as s:
        statuses = s.scalars(select(StatusChange.status).order_by(StatusChange.id)).all()
    assert statuses == ["arrived", "consented", "tutorial", "abandoned", "tutorial"]


def test_a_whole_run_to_completion_and_submission(client: TestClient, db: Database) -> None:
    participant, session_id = teaching_participant(client)
    assert (
        participant.client.get(
            "/api/participant/completion", headers=participant.headers
        ).status_code
        == 409
    )
    statuses = []
    finish = None
    while session_id is not None:
        view = participant.get(participant.session(session_id))
        statuses.append(view["participant"]["status"])
        demonstrate_each_task(participant, session_id)
        finish = participant.act(f"{participant.session(session_id)}/finish")
        session_id = finish["participant"]["current_session_id"]
        if session_id is not None:
            # Not readable before the end, neither in a response nor on its own.
            assert finish["participant"]["completion"] is None
            response = participant.client.get(
                "/api/participant/completion", headers=participant.headers
            )
            assert response.status_code == 409
    assert statuses == ["tutorial"] + ["teaching"] * 6
    completion = finish["participant"]["completion"]
    assert finish["participant"]["status"] == "completed"
    assert len(completion["code"]) == 10
    assert completion["submit_url"] == "https://workersandbox.mturk.com/mturk/externalSubmit"
    assert completion["submit_fields"] == {
        "assignmentId": "A1",
        "completionCode": completion["code"],
    }
    with db.read() as s:
        assert s.scalar(select(ParticipantRow.completion_code)) == completion["code"]
    # Shown again, identically, on refresh.
    assert participant.get("/api/participant/completion") == completion
    assert participant.get("/api/participant")["completion"] == completion
    assert participant.get("/api/participant")["progress"] == {"agent": 6, "of": 6}
    submitted = participant.act("/api/participant/submission")
    assert submitted["participant"]["status"] == "submitted"
    assert participant.post("/api/participant/submission").status_code == 409
    assert participant.get("/api/participant/completion") == completion
    with db.read() as s:
        changes = s.scalars(select(StatusChange).order_by(StatusChange.id)).all()
    assert [c.status for c in changes] == [
        "arrived",
        "consented",
        "tutorial",
        "teaching",
        "completed",
        "submitted",
    ]
    assert all(a.at <= b.at for a, b in pairwise(changes))


def test_the_tutorial_step_is_kept_on_the_server_and_never_goes_back(
    client: TestClient, db: Database
) -> None:
    participant, tutorial = teaching_participant(client)
    assert participant.get("/api/participant")["tutorial_step"] == 0
    assert participant.act("/api/participant/tutorial", step=4)["participant"]["status"] == (
        "tutorial"
    )
    # Another browser: the worker arrives again with the same ids and gets a new token.
    again = arrive(TestClient(client.app), "W1", "A1")
    assert again.status_code == 200, again.text
    elsewhere = Participant(client, again.json()["token"], participant.seq)
    assert elsewhere.get("/api/participant")["tutorial_step"] == 4
    participant = elsewhere
    participant.act("/api/participant/tutorial", step=2)  # a tab behind: the step stays
    assert participant.get("/api/participant")["tutorial_step"] == 4
    for body, status, words in (
        ({"step": -1}, 422, "step"),
        ({"step": 101}, 422, "step"),
        ({"step": "three"}, 422, "step"),
        ({}, 422, "step"),
    ):
        response = participant.post("/api/participant/tutorial", **body)
        assert response.status_code == status and words in response.text, response.text
    demonstrate_each_task(participant, tutorial)
    participant.act(f"/api/sessions/{tutorial}/finish")
    refused = participant.post("/api/participant/tutorial", step=5)
    assert refused.status_code == 409 and "not in progress" in refused.text
    assert participant.get("/api/participant")["tutorial_step"] == 4


def test_the_next_agent_is_opened_only_when_the_participant_begins_it(
    client: TestClient, db: Database
) -> None:
    participant, tutorial = teaching_participant(client)
    state = participant.get("/api/participant")
    # The tutorial began from the instructions page: it is opened.
    assert [s["opened"] for s in state["sessions"] if s["session_id"] == tutorial] == [True]
    demonstrate_each_task(participant, tutorial)
    following = participant.act(f"/api/sessions/{tutorial}/finish")["participant"][
        "current_session_id"
    ]
    current = participant.get("/api/participant")["sessions"]
    assert [s["opened"] for s in current if s["session_id"] == following] == [False]
    opened = participant.act(f"/api/sessions/{following}/open")
    assert opened["participant"]["current_session_id"] == following
    again = participant.act(f"/api/sessions/{following}/open")  # twice: still opened
    assert again["session"]["session_id"] == following
    current = participant.get("/api/participant")["sessions"]
    assert [s["opened"] for s in current if s["session_id"] == following] == [True]
    refused = participant.post(f"/api/sessions/{tutorial}/open")
    assert refused.status_code == 409 and "finished" in refused.text
