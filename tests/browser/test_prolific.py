"""A Prolific participant: the completion page sends them automatically to Prolific's completion
URL with the study's code (the only request that leaves the server, answered here by the test)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from playwright.sync_api import Page, Route

from tests.browser.conftest import (
    WAIT_MS,
    LiveServer,
    Study,
    Watch,
    domain_toml,
    run_live_server,
    study_toml,
)

pytestmark = pytest.mark.browser

CODE = "C1A2B3C4"
NAVIGATION = domain_toml("navigation", "wall")


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    config = study_toml(
        mode="prolific", domains_toml=NAVIGATION, learners='["cloning"]', agents=1
    ).replace('mode = "prolific"', f'mode = "prolific"\nprolific_code = "{CODE}"')
    yield from run_live_server(tmp_path_factory.mktemp("prolific-study"), config)


def test_a_prolific_participant_is_sent_back_with_the_code(page: Page, server: LiveServer) -> None:
    watch = Watch(server.url).attach(page)
    landed: list[str] = []

    def prolific(route: Route) -> None:
        landed.append(route.request.url)
        route.fulfill(status=200, content_type="text/html", body="<p>Prolific</p>")

    page.route("https://app.prolific.com/**", prolific)
    page.goto(f"{server.url}/study?PROLIFIC_PID=PID42&STUDY_ID=STUDY7&SESSION_ID=SESSION9")
    study = Study(page)
    page.click('[data-action="agree"]')
    page.click('[data-action="start"]')
    study.do_tutorial()
    for task in range(page.locator(".task").count()):
        study.demonstrate(task)
    study.press("n")
    page.locator('[data-action="confirm-next"]').click()
    # Sent back automatically (Prolific's guidance), without a click.
    page.wait_for_url("https://app.prolific.com/**", timeout=WAIT_MS)
    assert landed == [f"https://app.prolific.com/submissions/complete?cc={CODE}"]
    (row,) = server.query("SELECT status FROM participants WHERE worker_id = 'PID42'")
    assert row.status == "submitted"
    # Nothing but the redirect the participant asked for left the server.
    assert watch.foreign == landed
    watch.foreign.clear()
    watch.check()
