"""The study in a cross-site iframe, as on Mechanical Turk: the replica's page at one host
(127.0.0.1) and the study's iframe at another (localhost), so that the browser neither sends nor
keeps the study's SameSite=lax cookie in the iframe. The page sends the token the server gave it
in the X-Participant-Token header instead, and the participant is never lost (no 401)."""

from __future__ import annotations

import re
from collections.abc import Iterator
from urllib.parse import parse_qsl, urlencode, urlsplit

import pytest
from playwright.sync_api import Frame, Page, Request, Response, expect

from tests.browser.conftest import (
    WAIT_MS,
    LiveServer,
    Study,
    admin_login,
    domain_toml,
    next_state,
    run_live_server,
    study_toml,
)

pytestmark = pytest.mark.browser

NAVIGATION = domain_toml("navigation", "wall")
HEADER = "x-participant-token"


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    config = study_toml(mode="mturk", domains_toml=NAVIGATION, learners='["cloning"]', agents=1)
    yield from run_live_server(tmp_path_factory.mktemp("cross-site-study"), config)


def cross_site_frame(page: Page, server: LiveServer, worker: str) -> tuple[Frame, str]:
    """Accept the HIT on the replica (at 127.0.0.1) and open its study URL in the iframe at
    localhost, with turkSubmitTo pointing there as the replica would if it were served there."""
    # The replica's own same-site iframe load is answered empty: the participant arrives
    # only through the cross-site one.
    page.route(
        re.compile(re.escape(server.url) + r"/study\?"),
        lambda route: route.fulfill(status=200, content_type="text/html", body=""),
    )
    admin_login(page, server)
    page.fill("#workerId", worker)
    page.click('[data-action="accept"]')
    page.wait_for_url(re.compile(r"/mturk/work/\d+$"))
    src = str(page.locator("iframe.hitframe").get_attribute("src"))
    other = f"http://localhost:{urlsplit(server.url).port}"
    query = dict(parse_qsl(urlsplit(src).query))
    assert sorted(query) == ["assignmentId", "hitId", "turkSubmitTo", "workerId"]
    query["turkSubmitTo"] = other
    url = f"{other}/study?{urlencode(query)}"
    page.locator("iframe.hitframe").evaluate("(frame, url) => { frame.src = url; }", url)
    for _ in range(600):
        for frame in page.frames:
            if frame.url.startswith(f"{other}/study"):
                return frame, other
        page.wait_for_timeout(50)
    raise AssertionError("the cross-site iframe did not load")


def test_the_study_works_in_a_cross_site_iframe_without_its_cookie(
    page: Page, server: LiveServer
) -> None:
    refused: list[str] = []
    errors: list[str] = []
    api_requests: list[Request] = []

    def answered(response: Response) -> None:
        if response.status == 401 and "/api/" in response.url:
            refused.append(response.url)

    page.on("response", answered)
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.on("pageerror", lambda error: errors.append(str(error)))
    frame, other = cross_site_frame(page, server, "CROSSSITE1")
    page.on("request", lambda r: api_requests.append(r) if "/api/" in r.url else None)

    # Consent and start, each a request the server answers for this participant.
    expect(frame.locator('[data-action="agree"]')).to_be_visible(timeout=WAIT_MS)
    frame.locator('[data-action="agree"]').click()
    frame.locator('[data-action="start"]').click()
    study = Study(page, frame)
    expect(study.teach).to_have_attribute("data-kind", "tutorial", timeout=WAIT_MS)

    # A demonstrated move with a real key press.
    study.focus()
    study.press("d")
    study.wait_for("mode", "demonstrate")
    state = study.state()
    action = next(
        a
        for a in ("UP", "DOWN", "LEFT", "RIGHT")
        if next_state(study.environment, state, a) != state
    )
    study.move(action)
    study.wait_for("episode-actions", 1)

    # The browser kept no cookie for the iframe's host: the header did it all.
    assert [c for c in page.context.cookies(other) if c["name"] == "bam_participant"] == []
    assert api_requests and all(r.headers.get(HEADER) for r in api_requests)
    token = api_requests[-1].headers[HEADER]
    assert token not in frame.url
    (participant,) = server.query(
        "SELECT id, status FROM participants WHERE platform_participant_id = 'CROSSSITE1'"
    )
    assert participant.status == "tutorial"
    rows = server.query(
        "SELECT record FROM events WHERE participant_id = :p AND kind = 'move'", p=participant.id
    )
    assert [row.record for row in rows] == ["demonstration"]

    # A reload arrives again (the platform's ids find the participant), with a new token in
    # the page; the old one keeps working too (each browser of a participant keeps its own).
    frame.evaluate("() => window.location.reload()")
    expect(study.teach).to_have_attribute("data-episode-actions", "1", timeout=WAIT_MS)
    expect(study.teach).to_have_attribute("data-mode", "demonstrate")
    assert study.state() == next_state(study.environment, state, action)
    newer = api_requests[-1].headers[HEADER]
    assert newer != token
    old = page.request.get(f"{other}/api/participant", headers={"X-Participant-Token": token})
    assert old.ok and old.json()["participant_id"] == participant.id
    current = page.request.get(f"{other}/api/participant", headers={"X-Participant-Token": newer})
    assert current.ok and current.json()["participant_id"] == participant.id

    assert refused == []
    assert errors == []
