"""Arrival: MTurk, Prolific and lab parameters, previews, repeat workers, returned HITs,
resuming with and without the cookie, and bad links."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

from fastapi.testclient import TestClient
from sqlalchemy import func, select

from server.app.main import create_app
from server.app.storage.db import Database
from server.app.storage.models import Participant as ParticipantRow
from server.app.storage.models import StatusChange
from tests.support.server import (
    MTURK,
    Participant,
    arrive,
    demonstrate_each_task,
    make_settings,
    new_participant,
    study_config,
    teaching_participant,
)


def participants_in(db: Database) -> int:
    with db.read() as s:
        return int(s.scalar(select(func.count()).select_from(ParticipantRow)) or 0)


def test_mturk_arrival_creates_a_participant_with_an_httponly_cookie(
    client: TestClient, db: Database
) -> None:
    response = arrive(client)
    assert response.status_code == 201
    body = response.json()
    assert body["participant"]["status"] == "arrived"
    assert body["participant"]["platform"] == "mturk"
    assert body["participant"]["next_seq"] == 1
    assert len(body["token"]) >= 40
    cookie = response.headers["set-cookie"]
    assert body["token"] in cookie
    assert "HttpOnly" in cookie and "SameSite=lax" in cookie
    assert participants_in(db) == 1
    with db.read() as s:
        row = s.scalars(select(ParticipantRow)).one()
        assert body["token"] not in row.token_hash  # only a hash is stored
        assert (
            row.platform_participant_id == "W1"
            and row.platform_submission_id == "A1"
            and row.submit_to == MTURK
        )


def test_preview_creates_nothing(client: TestClient, db: Database) -> None:
    response = client.post(
        "/api/arrivals", json={"assignmentId": "ASSIGNMENT_ID_NOT_AVAILABLE", "hitId": "H1"}
    )
    assert response.status_code == 200
    assert response.json() == {
        "preview": True,
        "token": None,
        "resumed": False,
        "participant": None,
    }
    assert "set-cookie" not in response.headers
    page = client.get(
        "/study", params={"assignmentId": "ASSIGNMENT_ID_NOT_AVAILABLE", "hitId": "H1"}
    )
    assert page.status_code == 200
    assert "preview" in page.text.lower()
    assert "set-cookie" not in page.headers
    assert participants_in(db) == 0


def test_arriving_again_resumes_the_same_participant(client: TestClient, db: Database) -> None:
    first = arrive(client).json()
    # Same browser (the cookie is sent): same participant, the token stays.
    again = arrive(client)
    assert again.status_code == 200
    assert again.json()["resumed"] is True
    assert again.json()["token"] is None
    assert again.json()["participant"]["participant_id"] == first["participant"]["participant_id"]
    # A new browser without the cookie: the MTurk ids identify the participant, and the new
    # browser gets a token of its own; the first browser's goes on working.
    other = TestClient(client.app)
    resumed = arrive(other)
    assert resumed.status_code == 200
    assert resumed.json()["participant"]["participant_id"] == first["participant"]["participant_id"]
    assert resumed.json()["token"] not in (None, first["token"])
    old = client.get("/api/participant", headers={"X-Participant-Token": first["token"]})
    assert old.status_code == 200
    new = other.get("/api/participant", headers={"X-Participant-Token": resumed.json()["token"]})
    assert new.status_code == 200
    assert participants_in(db) == 1


def test_every_browser_of_a_participant_keeps_its_own_token(
    client: TestClient, db: Database
) -> None:
    browsers = 8
    start = threading.Barrier(browsers)

    def one(_: int) -> tuple[int, str]:
        other = TestClient(client.app)
        start.wait()
        response = arrive(other, "W4", "A4")
        assert response.status_code in (200, 201), response.text
        return response.json()["participant"]["participant_id"], response.json()["token"]

    with ThreadPoolExecutor(browsers) as pool:
        arrivals = list(pool.map(one, range(browsers)))
    assert len({participant for participant, _ in arrivals}) == 1
    tokens = [token for _, token in arrivals]
    assert len(set(tokens)) == browsers
    # Each browser's token works, and their requests share the participant's sequence.
    participants = [Participant(client, token) for token in tokens]
    participants[0].act("/api/participant/consent", agree=True)
    participants[1].seq = 2
    session = participants[1].act("/api/participant/start")["participant"]["current_session_id"]
    for seq, participant in enumerate(participants[2:], start=3):
        participant.seq = seq
        participant.act(f"/api/sessions/{session}/move", action="UP")
    for participant in participants:
        assert participant.get("/api/participant")["next_seq"] == browsers + 1
    assert participants_in(db) == 1


def test_a_worker_who_took_part_is_turned_away(client: TestClient, db: Database) -> None:
    participant = new_participant(client, "W7", "A1")
    participant.act("/api/participant/consent", agree=True)
    other = TestClient(client.app)
    response = arrive(other, "W7", "A2")
    assert response.status_code == 403
    assert response.json()["turned_away"] is True
    assert "already taken part" in response.json()["detail"]
    page = other.get(
        "/study",
        params={"assignmentId": "A3", "hitId": "H1", "workerId": "W7", "turkSubmitTo": MTURK},
    )
    assert page.status_code == 403
    assert "already taken part" in page.text
    assert participants_in(db) == 1


def test_a_worker_with_an_open_participation_is_turned_away(
    client: TestClient, db: Database
) -> None:
    # Before consenting to either: the first participation counts whatever its status.
    new_participant(client, "W8", "A1")
    refused = arrive(TestClient(client.app), "W8", "A2")
    assert refused.status_code == 403 and refused.json()["turned_away"] is True
    # Arriving again with the first assignment resumes it.
    assert arrive(TestClient(client.app), "W8", "A1").status_code == 200
    assert participants_in(db) == 1


def test_a_worker_who_declined_or_whose_assignment_was_returned_may_come_back(
    client: TestClient, db: Database
) -> None:
    declined = new_participant(client, "W8", "A1")
    declined.act("/api/participant/consent", agree=False)
    assert arrive(TestClient(client.app), "W8", "A2").status_code == 201
    # W8's A2 goes to W9 (W8 returned it on MTurk): W8 may take A3, and then not A2 again.
    assert arrive(TestClient(client.app), "W9", "A2").status_code == 201
    assert arrive(TestClient(client.app), "W8", "A3").status_code == 201
    assert arrive(TestClient(client.app), "W8", "A2").status_code == 403


def test_simultaneous_arrivals_of_one_worker_with_different_assignments_make_one_participation(
    client: TestClient, db: Database
) -> None:
    arrivals = 8
    start = threading.Barrier(arrivals)

    def one(number: int) -> tuple[int, str | None]:
        other = TestClient(client.app)
        start.wait()
        response = arrive(other, "W6", f"RA{number}")
        assert response.status_code in (201, 403), response.text
        if response.status_code == 403:
            return 403, None
        token = response.json()["token"]
        consent = other.post(
            "/api/participant/consent",
            json={"seq": 1, "agree": True},
            headers={"X-Participant-Token": token},
        )
        assert consent.status_code == 200, consent.text
        return 201, token

    with ThreadPoolExecutor(arrivals) as pool:
        answers = list(pool.map(one, range(arrivals)))
    assert sorted(status for status, _ in answers) == [201] + [403] * (arrivals - 1)
    assert participants_in(db) == 1


def test_repeat_workers_are_accepted_when_the_study_allows_them(db: Database, executor) -> None:
    settings = make_settings(db.engine.url.render_as_string(hide_password=False))
    app = create_app(settings, study_config(allow_repeat_workers=True), db=db, executor=executor)
    with TestClient(app) as client:
        participant = new_participant(client, "W7", "A1")
        participant.act("/api/participant/consent", agree=True)
        assert arrive(TestClient(app), "W7", "A2").status_code == 201


def test_a_returned_assignment_goes_to_another_worker(client: TestClient, db: Database) -> None:
    first, tutorial = teaching_participant(client, "W1", "A1")
    second = arrive(TestClient(client.app), "W2", "A1")
    assert second.status_code == 201
    assert second.json()["participant"]["participant_id"] == 2
    assert first.get("/api/participant")["status"] == "returned"
    refused = first.post(f"/api/sessions/{tutorial}/move", action="UP")
    assert refused.status_code == 409 and "returned" in refused.json()["detail"]
    with db.read() as s:
        statuses = s.scalars(
            select(StatusChange.status)
            .where(StatusChange.participant_id == 1)
            .order_by(StatusChange.id)
        ).all()
    assert statuses == ["arrived", "consented", "tutorial", "returned"]


def test_a_returned_worker_cannot_take_the_assignment_back_from_its_holder(
    client: TestClient, db: Database
) -> None:
    first, tutorial = teaching_participant(client, "W1", "A1")
    second_client = TestClient(client.app)
    arrived = arrive(second_client, "W2", "A1")
    assert arrived.status_code == 201
    second = Participant(second_client, arrived.json()["token"])
    second.act("/api/participant/consent", agree=True)

    def statuses() -> list[tuple[int, str]]:
        with db.read() as s:
            rows = s.execute(
                select(ParticipantRow.id, ParticipantRow.status).order_by(ParticipantRow.id)
            ).all()
        return [(row.id, row.status) for row in rows]

    before = statuses()
    assert before == [(1, "returned"), (2, "consented")]
    # W1 opens the old study URL in a new browser: W2 holds the assignment and keeps it.
    again = arrive(TestClient(client.app), "W1", "A1")
    assert again.status_code == 409, again.text
    assert again.json()["turned_away"] is True
    assert "returned" in again.json()["detail"] and "another worker" in again.json()["detail"]
    page = TestClient(client.app).get(
        "/study",
        params={"assignmentId": "A1", "hitId": "H1", "workerId": "W1", "turkSubmitTo": MTURK},
    )
    assert page.status_code == 409 and "You returned this task" in page.text
    assert statuses() == before
    # The holder goes on; the one who returned it is still refused.
    assert second.act("/api/participant/start")["participant"]["status"] == "tutorial"
    assert first.post(f"/api/sessions/{tutorial}/move", action="UP").status_code == 409


def test_worker_ids_are_compared_whatever_their_case(client: TestClient, db: Database) -> None:
    participant = new_participant(client, "AW7", "A1")
    participant.act("/api/participant/consent", agree=True)
    # The same worker, its id in lower case: a new assignment is a second participation.
    refused = arrive(TestClient(client.app), "aw7", "A2")
    assert refused.status_code == 403 and "already taken part" in refused.json()["detail"]
    # With the same assignment, it is the same participation, resumed (not taken over).
    resumed = arrive(TestClient(client.app), "aw7", "A1")
    assert resumed.status_code == 200, resumed.text
    assert resumed.json()["participant"]["participant_id"] == 1
    assert resumed.json()["participant"]["status"] == "consented"
    assert participants_in(db) == 1


def test_bad_arrivals_are_refused_and_create_nothing(client: TestClient, db: Database) -> None:
    cases = [
        ({"assignmentId": "A1", "workerId": "W1", "turkSubmitTo": MTURK}, 400, "hitId"),
        (
            {
                "assignmentId": "A1",
                "hitId": "H1",
                "workerId": "W1",
                "turkSubmitTo": "https://evil.example",
            },
            400,
            "turkSubmitTo",
        ),
        (
            {
                "assignmentId": "A1",
                "hitId": "H1",
                "workerId": "W1",
                "turkSubmitTo": "http://www.mturk.com",
            },
            400,
            "https",
        ),
        (
            {"assignmentId": "A 1", "hitId": "H1", "workerId": "W1", "turkSubmitTo": MTURK},
            422,
            "pattern",
        ),
        (
            {
                "assignmentId": "A1",
                "hitId": "H1",
                "workerId": "W1",
                "turkSubmitTo": MTURK,
                "PROLIFIC_PID": "P",
            },
            400,
            "both",
        ),
        ({"PROLIFIC_PID": "P1", "STUDY_ID": "S1", "SESSION_ID": "X1"}, 403, "Prolific"),
        ({}, 403, "Mechanical Turk"),
        ({"workerid": "W1"}, 422, "extra"),
    ]
    for body, status, words in cases:
        response = client.post("/api/arrivals", json=body)
        assert response.status_code == status, (body, response.text)
        assert words.lower() in response.text.lower(), (body, response.text)
    assert (
        client.post(
            "/api/arrivals", content=b"{not json", headers={"content-type": "application/json"}
        ).status_code
        == 422
    )
    page = client.get("/study", params={"assignmentId": "A1", "workerId": "W1"})
    assert page.status_code == 400 and "hitId" in page.text
    page = client.get(
        "/study", params={"assignmentId": "A1<script>", "hitId": "H", "workerId": "W"}
    )
    assert page.status_code == 400 and "<script>" not in page.text
    assert participants_in(db) == 0


def test_the_study_page_sets_the_cookie_and_the_api_accepts_it(
    client: TestClient, db: Database
) -> None:
    page = client.get(
        "/study",
        params={
            "assignmentId": "A1",
            "hitId": "H1",
            "workerId": "W1",
            "turkSubmitTo": MTURK,
            "extra": "ignored",
        },
    )
    assert page.status_code == 200
    assert "HttpOnly" in page.headers["set-cookie"]
    assert client.get("/api/participant").json()["status"] == "arrived"  # the cookie alone
    assert participants_in(db) == 1


def test_prolific_participants_complete_with_the_study_code(db: Database, executor) -> None:
    settings = make_settings(db.engine.url.render_as_string(hide_password=False))
    study = study_config(
        completion={"mode": "prolific", "prolific_code": "C0DE1"},
        domains=[{"name": "navigation", "environments": ["two-rooms"]}],
        learners=["cloning"],
        tutorial={"enabled": False},
        agents_per_environment=1,
    )
    app = create_app(settings, study, db=db, executor=executor)
    with TestClient(app) as client:
        mturk = arrive(client)
        assert mturk.status_code == 403
        response = client.post(
            "/api/arrivals", json={"PROLIFIC_PID": "P1", "STUDY_ID": "S1", "SESSION_ID": "X1"}
        )
        assert response.status_code == 201
        participant = Participant(client, response.json()["token"])
        participant.act("/api/participant/consent", agree=True)
        session_id = participant.act("/api/participant/start")["participant"]["current_session_id"]
        demonstrate_each_task(participant, session_id)
        done = participant.act(f"{participant.session(session_id)}/finish")
        completion = done["participant"]["completion"]
        assert completion["code"] == "C0DE1"
        assert (
            completion["redirect_url"] == "https://app.prolific.com/submissions/complete?cc=C0DE1"
        )
        assert participant.get("/api/participant/completion") == completion


def test_lab_participants_arrive_without_parameters(db: Database, executor) -> None:
    settings = make_settings(db.engine.url.render_as_string(hide_password=False))
    app = create_app(settings, study_config(completion={"mode": "lab"}), db=db, executor=executor)
    with TestClient(app) as client:
        first = client.post("/api/arrivals", json={})
        assert first.status_code == 201 and first.json()["participant"]["platform"] == "lab"
        again = client.post("/api/arrivals", json={})  # the cookie: the same participant
        assert again.status_code == 200 and again.json()["resumed"]
        other = TestClient(app).post("/api/arrivals", json={})
        assert other.status_code == 201
        assert arrive(client).status_code == 403  # this study is not on MTurk
    assert participants_in(db) == 2


def test_simultaneous_arrivals_of_one_worker_make_one_participant(
    client: TestClient, db: Database
) -> None:
    def one(_: int) -> int:
        response = arrive(TestClient(client.app), "W5", "A5")
        assert response.status_code in (200, 201), response.text
        return response.json()["participant"]["participant_id"]

    with ThreadPoolExecutor(6) as pool:
        ids = set(pool.map(one, range(6)))
    assert len(ids) == 1
    assert participants_in(db) == 1


# turkSubmitTo values a browser and Python's URL parser read differently, or that point
# elsewhere: each is refused on the API and on the study page, and creates nothing.
CRAFTED_SUBMIT_TO = [
    "https://evil.example\\@www.mturk.com",
    "https://evil.example\\www.mturk.com",
    "https://user:pw@www.mturk.com",
    "https://www.mturk.com@evil.example",
    "https://www.mturk.com:99999",
    "https://www.mturk.com:443",
    "https://www.mturk.com:8443",
    "https://www.mturk.com.evil.example",
    "https://www.mturk.com/../@evil.example",
    "https://www.mturk.com/mturk",
    "https://www.mturk.com?x=1",
    "https://www.mturk.com#x",
    "https://www.mturk.com\t",
    "https://www.mturk.com\n.evil.example",
    "https://www.mturk.com\x00",
    " https://www.mturk.com",
    "//www.mturk.com",
    "http://www.mturk.com",
    "https://[::1",
    "https://[::1]",
    "http://evil.example",
    "javascript:alert(1)",
]


def test_crafted_submit_addresses_are_refused(client: TestClient, db: Database) -> None:
    for value in CRAFTED_SUBMIT_TO:
        params = {"assignmentId": "A1", "hitId": "H1", "workerId": "W1", "turkSubmitTo": value}
        response = client.post("/api/arrivals", json=params)
        assert response.status_code in (400, 422), (value, response.text)
        assert "turkSubmitTo" in str(response.json()["detail"]), value
        page = client.get("/study", params=params)
        assert page.status_code == 400, (value, page.text)
        assert "<form" not in page.text
    assert participants_in(db) == 0


def test_the_submit_url_is_built_from_the_accepted_origin(client: TestClient, db: Database) -> None:
    accepted = {
        "https://www.mturk.com": "https://www.mturk.com",
        "https://workersandbox.mturk.com/": "https://workersandbox.mturk.com",
        "HTTPS://WWW.MTURK.COM": "https://www.mturk.com",
        # The local replica: this server's own origin (the test client's is http://testserver).
        "http://testserver": "http://testserver",
    }
    for number, (value, origin) in enumerate(accepted.items()):
        response = arrive(TestClient(client.app), f"W{number}", f"A{number}", turkSubmitTo=value)
        assert response.status_code == 201, (value, response.text)
        with db.read() as s:
            stored = s.scalar(
                select(ParticipantRow.submit_to).where(
                    ParticipantRow.platform_participant_id == f"W{number}"
                )
            )
        assert stored == origin
    # Another port of this server's host is another origin.
    response = arrive(client, "W9", "A9", turkSubmitTo="http://testserver:8080")
    assert response.status_code == 400
