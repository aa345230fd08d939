"""A signed-in dashboard's changes come only from the server's own pages (the Origin checked on
every state-changing admin request made with the dashboard's cookie), and the admin cookie is
Secure whenever the server is reached over HTTPS."""

from __future__ import annotations

from fastapi.testclient import TestClient

from tests.app.routers.test_admin import sign_in
from tests.support.server import ADMIN_TOKEN, teaching_participant

ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
OWN = {"Origin": "http://testserver"}
EXCLUDE = "/api/admin/participants/1/exclusion"


def test_a_change_with_the_dashboards_cookie_needs_the_servers_own_origin(
    client: TestClient,
) -> None:
    teaching_participant(client)
    sign_in(client)
    for foreign in (
        {"Origin": "https://evil.example"},
        {"Origin": "null"},
        {"Origin": "http://testserver.evil.example"},
        {"Referer": "https://evil.example/page"},
        {},  # a browser always names the origin of a POST; a cookie without one is refused
    ):
        refused = client.post(EXCLUDE, json={"reason": "forged"}, headers=foreign)
        assert refused.status_code == 403, (foreign, refused.text)
        assert "this server's own pages" in refused.json()["detail"]
    # Nothing changed, and reading needs no origin.
    participant = client.get("/api/admin/participants/1").json()
    assert participant["excluded"] is False
    # From the dashboard's own page (Origin, or only a Referer of the same origin): accepted.
    assert client.post(EXCLUDE, json={"reason": "x"}, headers=OWN).status_code == 200
    referer = {"Referer": "http://testserver/dashboard"}
    included = client.post(
        "/api/admin/participants/1/inclusion", json={"reason": "y"}, headers=referer
    )
    assert included.status_code == 200, included.text


def test_the_admin_token_as_a_bearer_header_needs_no_origin(client: TestClient) -> None:
    """A script's token is no ambient credential: another site's page cannot send it."""
    teaching_participant(client)
    fresh = TestClient(client.app)
    answered = fresh.post(
        EXCLUDE, json={"reason": "x"}, headers={**ADMIN, "Origin": "https://elsewhere.example"}
    )
    assert answered.status_code == 200, answered.text


def test_another_sites_page_cannot_sign_the_browser_in(client: TestClient) -> None:
    refused = client.post(
        "/dashboard/login",
        data={"token": ADMIN_TOKEN, "next": "/dashboard"},
        headers={"Origin": "https://evil.example"},
        follow_redirects=False,
    )
    assert refused.status_code == 403
    assert client.cookies.get("bam_admin") is None
    signed_in = client.post(
        "/dashboard/login",
        data={"token": ADMIN_TOKEN, "next": "/dashboard"},
        headers=OWN,
        follow_redirects=False,
    )
    assert signed_in.status_code == 303


def test_the_admin_cookie_is_secure_over_https(client: TestClient) -> None:
    plain = sign_in(TestClient(client.app))
    assert plain
    over_http = TestClient(client.app).post(
        "/dashboard/login", data={"token": ADMIN_TOKEN}, follow_redirects=False
    )
    assert "secure" not in over_http.headers["set-cookie"].lower()
    over_https = TestClient(client.app, base_url="https://testserver").post(
        "/dashboard/login", data={"token": ADMIN_TOKEN}, follow_redirects=False
    )
    assert over_https.status_code == 303
    assert "; secure" in over_https.headers["set-cookie"].lower()
