"""The experimenter's endpoints behind the admin token."""

from __future__ import annotations

import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import httpx
import pytest
from fastapi.testclient import TestClient

from server.app.admin_auth import FAILURES_ALLOWED, SESSION_SECONDS
from server.app.main import create_app
from server.app.settings import Settings
from server.app.storage.db import Database
from server.commands.main import main
from tests.support.server import (
    ADMIN_TOKEN,
    demonstrate_each_task,
    live,
    make_settings,
    study_config,
    teaching_participant,
    wait_for_updates,
    wait_until_ready,
)

ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}


def test_the_admin_api_needs_the_token(
    client: TestClient, db: Database, executor: ProcessPoolExecutor
) -> None:
    for path in ["/api/admin/participants", "/api/admin/sessions", "/api/admin/export.zip"]:
        assert client.get(path).status_code == 401
        assert client.get(path, headers={"Authorization": "Bearer wrong"}).status_code == 401
        assert client.get(path, headers={"Authorization": ADMIN_TOKEN}).status_code == 401
        assert client.get(path, headers=ADMIN).status_code == 200
    # A participant's token is no admin token.
    participant, _ = teaching_participant(client)
    assert (
        client.get(
            "/api/admin/participants", headers={"Authorization": f"Bearer {participant.token}"}
        ).status_code
        == 401
    )
    # Without BAM_ADMIN_TOKEN the admin API is off.
    settings = Settings(database_url=db.engine.url.render_as_string(hide_password=False))
    with TestClient(create_app(settings, study_config(), db=db, executor=executor)) as other:
        response = other.get("/api/admin/participants", headers=ADMIN)
        assert response.status_code == 503 and "BAM_ADMIN_TOKEN" in response.text


def test_participants_sessions_exclusion_and_replay(client: TestClient, db: Database) -> None:
    participant, tutorial = teaching_participant(client)
    demonstrate_each_task(participant, tutorial)
    current = participant.act(f"/api/sessions/{tutorial}/finish")["participant"][
        "current_session_id"
    ]
    teaching_participant(TestClient(client.app), "W2", "A2")
    wait_for_updates(db)
    listing = client.get("/api/admin/participants", headers=ADMIN).json()
    assert [p["participant_id"] for p in listing] == [1, 2]
    first = listing[0]
    assert (
        first["platform_participant_id"] == "W1"
        and first["status"] == "teaching"
        and first["agents"] == 6
    )
    assert first["agents_finished"] == 0 and first["excluded"] is False and first["minutes"] >= 0
    assert (
        client.get("/api/admin/participants?status=tutorial", headers=ADMIN).json()[0][
            "participant_id"
        ]
        == 2
    )
    assert client.get("/api/admin/participants?status=nonsense", headers=ADMIN).status_code == 400
    detail = client.get("/api/admin/participants/1", headers=ADMIN).json()
    assert [c["status"] for c in detail["status_changes"]] == [
        "arrived",
        "consented",
        "tutorial",
        "teaching",
    ]
    assert [s["kind"] for s in detail["sessions"]] == ["tutorial"] + ["study"] * 6
    assert detail["sessions"][0]["learner"] == "cloning"
    assert client.get("/api/admin/participants/99", headers=ADMIN).status_code == 404
    # Live sessions: the ones being taught.
    live = client.get("/api/admin/sessions?live=true", headers=ADMIN).json()
    assert sorted(s["session_id"] for s in live) == sorted([current, _active(client, 2)])
    # The learning curve and the replay of the tutorial.
    curve = client.get(f"/api/admin/sessions/{tutorial}/evaluations", headers=ADMIN).json()
    assert [point["update_index"] for point in curve] == list(range(len(curve)))
    assert all(point["normalized_return"] is not None for point in curve)
    replay = client.get(f"/api/admin/sessions/{tutorial}/replay", headers=ADMIN).json()
    assert replay["start_state"] is not None and replay["environment"]["tasks"]
    assert [e["seq"] for e in replay["events"]] == sorted(e["seq"] for e in replay["events"])
    assert replay["events"][-1]["kind"] == "finish"
    assert client.get("/api/admin/sessions/999/replay", headers=ADMIN).status_code == 404
    # Exclusion: marked with a reason and undone; the flow goes on.
    excluded = client.post(
        "/api/admin/participants/1/exclusion", json={"reason": "bot"}, headers=ADMIN
    )
    assert excluded.status_code == 200
    assert excluded.json()["excluded"] is True and excluded.json()["exclusion_reason"] == "bot"
    assert excluded.json()["status"] == "teaching"
    assert (
        client.post(
            "/api/admin/participants/1/exclusion", json={"reason": "bot"}, headers=ADMIN
        ).status_code
        == 409
    )
    assert (
        client.post("/api/admin/participants/1/exclusion", json={}, headers=ADMIN).status_code
        == 422
    )
    participant.act(f"/api/sessions/{current}/move", action="UP")
    included = client.post(
        "/api/admin/participants/1/inclusion", json={"reason": "a real teacher"}, headers=ADMIN
    )
    assert included.json()["excluded"] is False
    assert [c["status"] for c in included.json()["status_changes"]][-2:] == ["excluded", "included"]
    assert (
        client.post(
            "/api/admin/participants/1/inclusion", json={"reason": "a real teacher"}, headers=ADMIN
        ).status_code
        == 409
    )


def test_the_evaluations_of_an_unknown_session_are_not_found(
    client: TestClient, db: Database
) -> None:
    """404 with the reason, not an empty learning curve."""
    _, tutorial = teaching_participant(client)
    assert (
        client.get(f"/api/admin/sessions/{tutorial}/evaluations", headers=ADMIN).status_code == 200
    )
    unknown = tutorial + 1000
    response = client.get(f"/api/admin/sessions/{unknown}/evaluations", headers=ADMIN)
    assert response.status_code == 404
    assert f"no learning session {unknown}" in response.text
    assert client.get(f"/api/admin/sessions/{unknown}/evaluations").status_code == 401


def _active(client: TestClient, participant_id: int) -> int:
    detail = client.get(f"/api/admin/participants/{participant_id}", headers=ADMIN).json()
    return next(s["session_id"] for s in detail["sessions"] if s["status"] == "active")


def test_public_study_information_and_health(client: TestClient) -> None:
    study = client.get("/api/study").json()
    assert study["completion_mode"] == "mturk" and "3.00 USD" in study["payment"]
    assert "bam" not in str(study).lower()
    health = wait_until_ready(client)
    assert health["status"] == "ok" and health["update_backlog"] >= 0


def test_serve_refuses_a_short_admin_token(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("BAM_DATABASE_URL", f"sqlite:///{tmp_path / 'study.db'}")
    monkeypatch.setenv("BAM_ADMIN_TOKEN", "hunter2hunter2")
    assert main(["serve", "--port", "1"]) == 2
    error = capsys.readouterr().err
    assert "BAM_ADMIN_TOKEN has 14 characters; it needs at least 16" in error
    assert "secrets.token_urlsafe()" in error
    assert not (tmp_path / "study.db").exists()  # refused before touching the database


def test_failed_sign_ins_are_limited_per_address(client: TestClient) -> None:
    state = client.app.state.server
    clock = [1000.0]
    state.sign_ins.clock = lambda: clock[0]
    other = TestClient(client.app, client=("192.0.2.7", 5000))
    for _ in range(FAILURES_ALLOWED):
        wrong = client.post("/dashboard/login", data={"token": "guess", "next": "/dashboard"})
        assert wrong.status_code == 401
    # Past the limit the address gets 429 with Retry-After, even with the right token, on the
    # login form and on the admin API alike.
    for response in (
        client.post("/dashboard/login", data={"token": ADMIN_TOKEN}, follow_redirects=False),
        client.get("/api/admin/participants", headers={"Authorization": "Bearer guess"}),
        client.get("/api/admin/participants", headers=ADMIN),
    ):
        assert response.status_code == 429, response.text
        assert response.headers["Retry-After"] == "60"
        assert "too many failed sign-ins" in response.text
    # Another address is not held up.
    assert other.get("/api/admin/participants", headers=ADMIN).status_code == 200
    # A minute after the first failure, one more try.
    clock[0] += 30
    assert client.get("/api/admin/sessions", headers=ADMIN).headers["Retry-After"] == "30"
    clock[0] += 30
    assert client.get("/api/admin/participants", headers=ADMIN).status_code == 200


def sign_in(client: TestClient) -> str:
    response = client.post(
        "/dashboard/login", data={"token": ADMIN_TOKEN, "next": "/dashboard"},
        follow_redirects=False,
    )  # fmt: skip
    assert response.status_code == 303
    cookie = client.cookies.get("bam_admin")
    assert cookie is not None and ADMIN_TOKEN not in cookie
    return cookie


def test_the_dashboard_cookie_is_a_session_that_expires_and_is_revoked(
    client: TestClient,
) -> None:
    state = client.app.state.server
    first = sign_in(client)
    second = sign_in(TestClient(client.app))
    assert first != second  # a random id per session, not a fixed value of the token
    copied = TestClient(client.app)
    copied.cookies.set("bam_admin", first)
    assert copied.get("/api/admin/participants").status_code == 200
    # Signing out revokes the session: the copy stops working, the other session goes on.
    assert client.post("/dashboard/logout", follow_redirects=False).status_code == 303
    assert copied.get("/api/admin/participants").status_code == 401
    other = TestClient(client.app)
    other.cookies.set("bam_admin", second)
    assert other.get("/api/admin/participants").status_code == 200
    # A changed expiry or signature is refused.
    session_id, expires, signature = second.split(".")
    for forged in (
        f"{session_id}.{int(expires) + 3600}.{signature}",
        f"{session_id}.{expires}.{'0' * len(signature)}",
        f"{session_id}.{expires}",
        "",
    ):
        forger = TestClient(client.app)
        forger.cookies.set("bam_admin", forged)
        assert forger.get("/api/admin/participants").status_code == 401
    # The session ends at its expiry.
    now = time.time()
    state.admin_sessions.clock = lambda: now + SESSION_SECONDS + 1
    assert other.get("/api/admin/participants").status_code == 401


def test_the_dashboard_excludes_and_includes_again_with_the_reasons(
    client: TestClient, db: Database
) -> None:
    teaching_participant(client)
    base = "/api/admin/participants"
    assert client.post(f"{base}/1/exclusion", json={"reason": "x"}).status_code == 401
    excluded = client.post(
        f"{base}/1/exclusion", json={"reason": "pressed keys at random"}, headers=ADMIN
    )
    assert excluded.status_code == 200, excluded.text
    assert excluded.json()["excluded"] is True
    assert excluded.json()["exclusion_reason"] == "pressed keys at random"
    again = client.post(f"{base}/1/exclusion", json={"reason": "twice"}, headers=ADMIN)
    assert again.status_code == 409 and "already excluded" in again.text
    for body in ({"reason": ""}, {}, {"reason": "x", "extra": 1}):
        assert client.post(f"{base}/1/inclusion", json=body, headers=ADMIN).status_code == 422
    assert (
        client.post(f"{base}/99/exclusion", json={"reason": "x"}, headers=ADMIN).status_code == 404
    )
    included = client.post(
        f"{base}/1/inclusion", json={"reason": "the log shows real teaching"}, headers=ADMIN
    )
    assert included.status_code == 200 and included.json()["excluded"] is False
    assert included.json()["exclusion_reason"] is None
    history = [(c["status"], c["note"]) for c in included.json()["status_changes"]][-2:]
    assert history == [
        ("excluded", "pressed keys at random"),
        ("included", "the log shows real teaching"),
    ]
    not_excluded = client.post(f"{base}/1/inclusion", json={"reason": "x"}, headers=ADMIN)
    assert not_excluded.status_code == 409 and "not excluded" in not_excluded.text


@pytest.mark.parametrize("backend", ["sqlite"], indirect=True)
@pytest.mark.parametrize(("proxies", "limited"), [("", True), ("127.0.0.1", False)])
def test_the_sign_in_limit_trusts_forwarded_addresses_only_from_named_proxies(
    db: Database, executor: ProcessPoolExecutor, proxies: str, limited: bool
) -> None:
    """Served as `serve` serves it: a client that makes up a new X-Forwarded-For for each guess
    is still one address, unless BAM_FORWARDED_ALLOW_IPS names it as a proxy."""
    settings = make_settings(
        db.engine.url.render_as_string(hide_password=False), forwarded_allow_ips=proxies
    )
    app = create_app(settings, study_config(), db=db, executor=executor)
    guesses = FAILURES_ALLOWED + 5
    with live(app) as url, httpx.Client(base_url=url, timeout=30) as http:
        statuses = [
            http.get(
                "/api/admin/participants",
                headers={"Authorization": "Bearer guess", "X-Forwarded-For": f"198.51.100.{n}"},
            ).status_code
            for n in range(guesses)
        ]
    if limited:
        assert statuses == [401] * FAILURES_ALLOWED + [429] * (guesses - FAILURES_ALLOWED)
    else:
        assert statuses == [401] * guesses
