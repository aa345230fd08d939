"""Sequence numbers: a retried request is answered identically and stored once; a request out
of order, or a sequence number reused for another request, gets 409."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

from fastapi.testclient import TestClient
from sqlalchemy import select

from server.app.storage.db import Database
from server.app.storage.models import Event
from tests.support.server import count_events, teaching_participant


def test_a_retried_request_is_answered_identically_and_stored_once(
    client: TestClient, db: Database
) -> None:
    participant, session_id = teaching_participant(client)
    base = participant.session(session_id)
    participant.act(f"{base}/mode", mode="demonstrate")
    body = {"seq": participant.seq, "action": "UP"}
    first = client.post(f"{base}/move", json=body, headers=participant.headers)
    events = count_events(db)
    # Later requests happen, then the lost answer is asked for again.
    participant.seq = first.json()["participant"]["next_seq"]
    participant.act(f"{base}/move", action="DOWN")
    again = client.post(f"{base}/move", json=body, headers=participant.headers)
    assert again.status_code == 200
    assert again.content == first.content
    assert count_events(db) == events + 1
    with db.read() as s:
        seqs = s.scalars(
            select(Event.seq).where(Event.participant_id == 1).order_by(Event.id)
        ).all()
    assert seqs == list(range(1, len(seqs) + 1))


def test_a_sequence_number_reused_for_another_request_is_refused(
    client: TestClient, db: Database
) -> None:
    participant, session_id = teaching_participant(client)
    base = participant.session(session_id)
    used = participant.seq - 1
    events = count_events(db)
    response = client.post(
        f"{base}/move", json={"seq": used, "action": "UP"}, headers=participant.headers
    )
    assert response.status_code == 409
    assert f"sequence number {used} was already used" in response.json()["detail"]
    ahead = client.post(
        f"{base}/reset", json={"seq": participant.seq + 3}, headers=participant.headers
    )
    assert ahead.status_code == 409 and "out of order" in ahead.json()["detail"]
    assert f"the next is {participant.seq}" in ahead.json()["detail"]
    assert count_events(db) == events


def test_concurrent_duplicates_are_stored_once(client: TestClient, db: Database) -> None:
    participant, session_id = teaching_participant(client)
    base = participant.session(session_id)
    events = count_events(db)
    body = {"seq": participant.seq, "action": "LEFT"}

    def send(_: int) -> tuple[int, bytes]:
        response = client.post(f"{base}/move", json=body, headers=participant.headers)
        return response.status_code, response.content

    with ThreadPoolExecutor(8) as pool:
        answers = list(pool.map(send, range(8)))
    assert {status for status, _ in answers} == {200}
    assert len({content for _, content in answers}) == 1
    assert count_events(db) == events + 1


def test_participants_do_not_share_sequence_numbers(client: TestClient, db: Database) -> None:
    first, first_session = teaching_participant(client)
    second, second_session = teaching_participant(TestClient(client.app), "W2", "A2")
    assert first.seq == second.seq == 3
    first.act(f"{first.session(first_session)}/move", action="UP")
    second.act(f"{second.session(second_session)}/move", action="UP")
    assert first.get("/api/participant")["next_seq"] == 4
    assert second.get("/api/participant")["next_seq"] == 4
