"""An arrival beyond the study's limit of participants at once waits on a page that passes
axe-core and lets them in by itself when a place frees; the dashboard shows the queue."""

from __future__ import annotations

import re
from collections.abc import Iterator

import pytest
from playwright.sync_api import Browser, Page, expect

from tests.browser.conftest import (
    LiveServer,
    Watch,
    admin_login,
    axe_violations,
    domain_toml,
    run_live_server,
    study_toml,
)

pytestmark = pytest.mark.browser

ADMITTED_WITHIN_MS = 60_000  # the page asks every 3 s: a generous bound
# The server's own CPU seconds per update, as timed at start (the timing itself is tested in
# tests/commands/test_server_share.py).
SERVER_SHARE = 0.0437


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    config = "max_active_participants = 1\n" + study_toml(
        mode="lab", domains_toml=domain_toml("navigation", "wall"), learners='["cloning"]', agents=1
    )
    yield from run_live_server(
        tmp_path_factory.mktemp("waiting-study"),
        config,
        measure_capacity=True,
        server_share=lambda stop: SERVER_SHARE,
    )


def test_an_arrival_beyond_the_limit_waits_and_goes_in_when_a_place_frees(
    page: Page, browser: Browser, server: LiveServer
) -> None:
    first = browser.new_context()
    dashboard = browser.new_context().new_page()
    try:
        arrived = first.request.post(f"{server.url}/api/arrivals", data={})
        assert arrived.status == 201, arrived.text()
        watch = Watch(server.url).attach(page)
        page.goto(f"{server.url}/study")
        expect(page.get_by_role("heading", level=1)).to_have_text("The study is full for a moment")
        expect(page.get_by_role("status")).to_have_text("You are next in line.")
        assert axe_violations(page) == []
        (waiting,) = server.query("SELECT status, domain FROM participants WHERE id = 2")
        assert waiting.status == "waiting" and waiting.domain is None

        # The dashboard shows the one place taken and the one participant waiting.
        admin_login(dashboard, server, "/dashboard")
        queue = dashboard.locator("#queue")
        expect(queue.locator('[data-queue="active"] dd')).to_have_text("1 / 1")
        expect(queue.locator('[data-queue="waiting"] dd')).to_have_text("1")
        expect(queue.locator('[data-queue="pending"] dd')).to_have_text("0")
        # Once the reference updates are timed (the page refreshes itself): the capacity, and
        # the longest update with its learner and environment.
        longest = queue.locator('[data-queue="longest"]')
        expect(longest.locator("dd")).to_have_text(
            re.compile(r"^\d+\.\d (s|min)$"), timeout=ADMITTED_WITHIN_MS
        )
        expect(longest.locator("dt")).to_contain_text("cloning in wall")
        capacity = queue.locator('[data-queue="capacity"]')
        expect(capacity.locator("dd")).to_have_text(re.compile(r"^\d+$"))
        expect(capacity.locator("dt")).to_contain_text(
            "the server's own work 0.04 s of a core per update"
        )
        assert axe_violations(dashboard) == []

        # The first participant declines: the waiting page opens the study by itself.
        declined = first.request.post(
            f"{server.url}/api/participant/consent", data={"seq": 1, "agree": False}
        )
        assert declined.status == 200, declined.text()
        expect(page.locator('[data-action="agree"]')).to_be_visible(timeout=ADMITTED_WITHIN_MS)
        (admitted,) = server.query("SELECT status FROM participants WHERE id = 2")
        assert admitted.status == "arrived"
        watch.check()
    finally:
        dashboard.context.close()
        first.close()
