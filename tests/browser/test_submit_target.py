"""The completion form never posts to another host: crafted ``turkSubmitTo`` values (which
Python's URL parser and Chromium read differently, or which carry user info, a port, a path)
get the refusal page with no form; accepted ones give a form whose action Chromium resolves to
the accepted origin, and "Submit the HIT" sends the worker's code there and nowhere else."""

from __future__ import annotations

from collections.abc import Iterator
from urllib.parse import urlencode

import pytest
from playwright.sync_api import Page, Route, expect

from server.commands.simulated import LightClient, SimulatedParticipant, TeachingPlan
from tests.browser.conftest import (
    WAIT_MS,
    LiveServer,
    domain_toml,
    run_live_server,
    study_toml,
)

pytestmark = pytest.mark.browser

CRAFTED = [
    "https://evil.example\\@www.mturk.com",
    "https://evil.example\\\\www.mturk.com",
    "https://user:pw@www.mturk.com",
    "https://www.mturk.com@evil.example",
    "https://www.mturk.com:99999",
    "https://www.mturk.com:8443",
    "https://www.mturk.com\t.evil.example",
    "https://www.mturk.com/../@evil.example",
    "https://[::1",
    "//evil.example",
]


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    config = study_toml(
        mode="mturk",
        domains_toml=domain_toml("navigation", "two-rooms"),
        learners='["cloning"]',
        agents=1,
        tutorial=False,
    )
    yield from run_live_server(tmp_path_factory.mktemp("submit-target"), config)


def study_url(server: LiveServer, worker: str, submit_to: str) -> str:
    params = {"assignmentId": f"A{worker}", "hitId": "H1", "workerId": worker}
    return f"{server.url}/study?{urlencode({**params, 'turkSubmitTo': submit_to})}"


def record_requests(page: Page, server: LiveServer) -> list[tuple[str, str]]:
    """Every request the page makes off this server is answered here and listed."""
    sent: list[tuple[str, str]] = []

    def elsewhere(route: Route) -> None:
        sent.append((route.request.method, route.request.url))
        route.fulfill(status=200, content_type="text/html", body="<p>recorded</p>")

    page.route(lambda url: not url.startswith(server.url + "/"), elsewhere)
    return sent


def complete_over_the_api(server: LiveServer, token: str) -> None:
    """Teach the participant's one agent to the end through the JSON API, with its token."""
    with LightClient(server.url) as client:
        simulated = SimulatedParticipant(
            server.url, 0, 0, TeachingPlan(max_rounds=1, agent_try_probability=0.0), client=client
        )
        simulated.token = token
        simulated.act("/api/participant/consent", "consent", agree=True)
        current = simulated.act("/api/participant/start", "start")["participant"][
            "current_session_id"
        ]
        while current is not None:
            current = simulated.teach(current)["participant"]["current_session_id"]


def test_crafted_submit_addresses_get_no_form(page: Page, server: LiveServer) -> None:
    sent = record_requests(page, server)
    for number, value in enumerate(CRAFTED):
        response = page.goto(study_url(server, f"X{number}", value))
        assert response is not None and response.status == 400, value
        expect(page.locator("body")).to_contain_text("turkSubmitTo")
        assert page.locator("form").count() == 0, value
    assert sent == []
    assert server.query("SELECT count(*) FROM participants")[0][0] == 0


@pytest.mark.parametrize(
    ("value", "origin"),
    [
        ("HTTPS://WWW.MTURK.COM/", "https://www.mturk.com"),
        ("https://workersandbox.mturk.com", "https://workersandbox.mturk.com"),
        ("{server}/", "{server}"),
    ],
)
def test_the_completion_form_posts_to_the_accepted_origin(
    page: Page, server: LiveServer, value: str, origin: str
) -> None:
    value, origin = value.format(server=server.url), origin.format(server=server.url)
    worker = "W" + "".join(ch for ch in value if ch.isalnum())[:40]
    sent = record_requests(page, server)
    page.goto(study_url(server, worker, value))
    token = next(c["value"] for c in page.context.cookies() if c["name"] == "bam_participant")
    complete_over_the_api(server, token)
    page.reload()
    form = page.locator("form.submit-form")
    expect(form).to_be_visible(timeout=WAIT_MS)
    # Chromium's own reading of the form's target.
    action = form.evaluate("form => new URL(form.action).origin + new URL(form.action).pathname")
    assert action == f"{origin}/mturk/externalSubmit"
    with page.expect_request(lambda r: r.method == "POST" and "externalSubmit" in r.url) as posted:
        page.click('[data-action="submit-hit"]')
    request = posted.value
    page.wait_for_url(f"{origin}/mturk/externalSubmit")
    assert request.url == f"{origin}/mturk/externalSubmit"
    assert f"assignmentId=A{worker}" in (request.post_data or "")
    foreign = [url for _, url in sent]
    if origin == server.url:
        assert foreign == []
    else:
        assert foreign == [f"{origin}/mturk/externalSubmit"]
