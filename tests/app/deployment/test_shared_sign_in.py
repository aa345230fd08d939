"""The experimenter's sign-in on a deployment of several servers: a dashboard cookie one server
gave works on the others, signing out on one ends it on all, and the failed sign-ins of an
address are counted across all of them. Here the servers are apps on one database (the
test of the whole deployment, tests/app/deployment/test_behind_a_proxy.py, runs processes)."""

from __future__ import annotations

from fastapi.testclient import TestClient

from server.app.admin_auth import FAILURES_ALLOWED
from server.app.main import create_app
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.study_file import StudyConfig
from tests.support.server import ADMIN_TOKEN

ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
PARTICIPANTS = "/api/admin/participants"


def servers(db: Database, settings: Settings, study: StudyConfig, count: int) -> list[TestClient]:
    """``count`` servers of one deployment: apps of their own on the same database."""
    return [TestClient(create_app(settings, study, db=db)) for _ in range(count)]


def test_a_dashboard_cookie_from_one_server_works_on_every_server(
    db: Database, settings: Settings, study: StudyConfig
) -> None:
    first, second, third = servers(db, settings, study, 3)
    signed_in = first.post(
        "/dashboard/login", data={"token": ADMIN_TOKEN, "next": "/dashboard"},
        follow_redirects=False,
    )  # fmt: skip
    assert signed_in.status_code == 303
    cookie = first.cookies.get("bam_admin")
    assert cookie is not None
    for other in (second, third):
        other.cookies.set("bam_admin", cookie)
        assert other.get(PARTICIPANTS).status_code == 200
    # Signed out on the second server: the cookie stops working on all three.
    assert second.post("/dashboard/logout", follow_redirects=False).status_code == 303
    for client in (first, third):
        assert client.get(PARTICIPANTS).status_code == 401


def test_failed_sign_ins_count_across_the_servers(
    db: Database, settings: Settings, study: StudyConfig
) -> None:
    deployment = servers(db, settings, study, 3)
    for attempt in range(FAILURES_ALLOWED):  # spread over the servers, as a proxy spreads them
        wrong = deployment[attempt % 3].post("/dashboard/login", data={"token": "guess"})
        assert wrong.status_code == 401, wrong.text
    for client in deployment:  # every server refuses the address now, even the right token
        refused = client.get(PARTICIPANTS, headers=ADMIN)
        assert refused.status_code == 429, refused.text
        assert "too many failed sign-ins" in refused.text
    other = TestClient(create_app(settings, study, db=db), client=("192.0.2.7", 5000))
    assert other.get(PARTICIPANTS, headers=ADMIN).status_code == 200
