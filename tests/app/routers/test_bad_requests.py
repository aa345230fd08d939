"""Requests no server should answer with a 5xx: non-finite numbers and lone surrogates in JSON,
NUL in text, path ids past the database's integer range, loose types. Each gets a 4xx with a
JSON message, and the stored data is unchanged."""

from __future__ import annotations

from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from server.app.errors import ApiError
from server.app.storage.db import Database
from server.app.storage.models import Event, Participant, StatusChange
from tests.support.server import ADMIN_TOKEN, MTURK, teaching_participant

ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
TOO_LARGE_IDS = ["2147483648", "9223372036854775808", "0", "-1"]


def stored(db: Database) -> tuple[Any, ...]:
    """Everything a refused request could have changed."""
    with db.read() as s:
        participants = s.execute(
            select(
                Participant.id,
                Participant.status,
                Participant.next_seq,
                Participant.excluded_at,
                Participant.exclusion_reason,
                Participant.token_hash,
            ).order_by(Participant.id)
        ).all()
        events = s.scalar(select(func.count()).select_from(Event))
        changes = s.scalar(select(func.count()).select_from(StatusChange))
    return tuple(participants), events, changes


def refused(response: Any, *statuses: int) -> str:
    assert response.status_code in (statuses or (400, 404, 409, 422)), response.text
    detail = response.json()["detail"]
    assert detail
    return str(detail)


def raw(client: TestClient, path: str, body: bytes, headers: dict[str, str] | None = None) -> Any:
    return client.post(
        path, content=body, headers={"content-type": "application/json", **(headers or {})}
    )


@pytest.fixture
def participant(client: TestClient) -> Any:
    return teaching_participant(client)


def test_bad_requests_get_4xx_and_change_nothing(
    client: TestClient, db: Database, participant: Any
) -> None:
    learner, session = participant
    token = learner.headers
    before = stored(db)
    arrival = {"assignmentId": "A2", "hitId": "H1", "workerId": "W2"}

    # A bracketed host, on the API and on the study page.
    refused(client.post("/api/arrivals", json={**arrival, "turkSubmitTo": "https://[::1"}), 400)
    page = client.get("/study", params={**arrival, "turkSubmitTo": "https://[::1"})
    assert page.status_code == 400

    # NaN and Infinity anywhere in a JSON body.
    refused(raw(client, "/api/arrivals", b'{"workerId": NaN}'), 422)
    refused(raw(client, "/api/arrivals", b'{"assignmentId": "A2", "hitId": -Infinity}'), 422)
    for path in ("/api/participant/consent", f"/api/sessions/{session}/task"):
        refused(raw(client, path, b'{"seq": Infinity, "agree": true}', token), 422)
        refused(raw(client, path, b'{"seq": NaN, "task": 0}', token), 422)
    refused(raw(client, "/api/admin/participants/1/exclusion", b'{"reason": NaN}', ADMIN), 422)
    refused(client.get(f"/api/sessions/{session}/learning?wait=nan", headers=token), 422)
    refused(client.get(f"/api/sessions/{session}/learning?wait=inf", headers=token), 422)

    # Lone surrogates in any string, NUL in any string (refused on both backends alike).
    surrogate = b'{"assignmentId": "\\ud800", "hitId": "H1", "workerId": "W2", "turkSubmitTo": "x"}'
    refused(raw(client, "/api/arrivals", surrogate), 422)
    submit_to = (
        b'{"assignmentId": "A2", "hitId": "H1", "workerId": "W2", "turkSubmitTo": "\\udfff"}'
    )
    refused(raw(client, "/api/arrivals", submit_to), 422)
    refused(raw(client, f"/api/sessions/{session}/mode", b'{"seq": 1, "mode": "\\ud800"}', token))
    for reason in (b'"\\ud800"', b'"a\\u0000b"', b'"\\udc00 why"'):
        body = b'{"reason": ' + reason + b"}"
        detail = refused(raw(client, "/api/admin/participants/1/exclusion", body, ADMIN), 422)
        assert "NUL" in detail or "unicode" in detail.lower()
    nul = {**arrival, "turkSubmitTo": MTURK, "workerId": "W\x002"}
    refused(client.post("/api/arrivals", json=nul), 422)

    # Path ids past the integer columns' range (or below 1), participant and admin paths.
    for number in TOO_LARGE_IDS:
        refused(client.get(f"/api/sessions/{number}", headers=token), 422)
        refused(client.get(f"/api/sessions/{number}/learning", headers=token), 422)
        refused(client.post(f"/api/sessions/{number}/move", json={"seq": learner.seq, "action": "UP"}, headers=token), 422)  # fmt: skip
        for path in (
            f"/api/admin/participants/{number}",
            f"/api/admin/sessions/{number}/evaluations",
            f"/api/admin/sessions/{number}/replay",
        ):
            refused(client.get(path, headers=ADMIN), 422)
        refused(client.post(f"/api/admin/participants/{number}/exclusion", json={"reason": "r"}, headers=ADMIN), 422)  # fmt: skip
        refused(client.post(f"/api/admin/participants/{number}/inclusion", json={"reason": "r"}, headers=ADMIN), 422)  # fmt: skip

    # Loose coercions: the API takes the JSON types it documents.
    for body in (
        {"seq": True, "agree": True},
        {"seq": "1_0", "agree": True},
        {"seq": str(learner.seq), "agree": True},
        {"seq": float(learner.seq), "agree": True},
        {"seq": learner.seq, "agree": "yes"},
        {"seq": learner.seq, "agree": 1},
    ):
        detail = refused(client.post("/api/participant/consent", json=body, headers=token), 422)
        assert "valid" in detail
    refused(learner.post(f"/api/sessions/{session}/task", task="0"), 422)
    refused(learner.post(f"/api/sessions/{session}/feedback", feedback="1"), 422)
    refused(client.post("/api/arrivals", json={**arrival, "turkSubmitTo": MTURK, "hitId": 1}), 422)

    assert stored(db) == before
    # The participant goes on where it was.
    learner.act(f"/api/sessions/{session}/mode", mode="demonstrate")


def test_every_422_has_its_detail_as_a_list_of_problems(
    client: TestClient, db: Database, participant: Any
) -> None:
    """The documented shape of a 422 (HTTPValidationError): FastAPI's own (a bad query value, a
    bad body) and any the server raises itself."""
    learner, session = participant
    before = stored(db)

    def refuse() -> None:
        raise ApiError(422, "reason: NUL (\\x00) is not allowed in text")

    client.app.add_api_route("/api/probe-422", refuse)
    responses = [
        client.get(f"/api/sessions/{session}/learning?wait=%00", headers=learner.headers),
        client.post("/api/admin/participants/1/exclusion", json={"reason": ""}, headers=ADMIN),
        client.get("/api/probe-422"),
    ]
    for response in responses:
        assert response.status_code == 422, response.text
        detail = response.json()["detail"]
        assert isinstance(detail, list) and detail, detail
        for problem in detail:
            assert isinstance(problem["loc"], list) and problem["msg"] and problem["type"]
    assert responses[-1].json()["detail"] == [
        {"type": "value_error", "loc": [], "msg": "reason: NUL (\\x00) is not allowed in text"}
    ]
    assert stored(db) == before
    schema = client.get("/openapi.json").json()["components"]["schemas"]
    assert schema["HTTPValidationError"]["properties"]["detail"]["type"] == "array"
