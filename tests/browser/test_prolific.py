"""A Prolific participant: the completion page sends them automatically to Prolific's completion
URL with the study's code (the only request that leaves the server, answered here by the test)."""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest
from playwright.sync_api import Page, Route, expect

from server.app.storage.db import Database
from server.app.storage.models import Bonus, Participant, utcnow
from tests.browser.conftest import (
    WAIT_MS,
    LiveServer,
    Study,
    Watch,
    admin_login,
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
    (row,) = server.query("SELECT status FROM participants WHERE platform_participant_id = 'PID42'")
    assert row.status == "submitted"
    # Nothing but the redirect the participant asked for left the server.
    assert watch.foreign == landed
    watch.foreign.clear()
    watch.check()


def test_a_bonus_in_doubt_is_shown_as_such_and_settled_from_the_dashboard(
    page: Page, server: LiveServer
) -> None:
    """A Prolific bonus whose pay failed after it may have paid: neither paid nor unpaid on the
    dashboard, with how it settles; Settle it sends it again with its own token, and the answer
    (here: no record of that submission to settle it by) is shown by the bonus."""
    db = Database.from_url(server.database_url)
    with db.write() as s:
        p = Participant(
            token_hash=os.urandom(32).hex(),
            platform="prolific",
            platform_participant_id="PIDDOUBT",
            platform_submission_id="SESSIONDOUBT",
            platform_study_id="STUDYDOUBT",
            status="submitted",
        )
        s.add(p)
        s.flush()
        s.add(
            Bonus(
                participant_id=p.id,
                platform_submission_id="SESSIONDOUBT",
                platform_participant_id="PIDDOUBT",
                amount_cents=125,
                currency="GBP",
                reason="Taught well",
                unique_token="doubt-token-1",
                backend="prolific-replica",
                state="in_doubt",
                setup_id="b" * 24,
                requested_at=utcnow(),
                pay_sent_at=utcnow(),
            )
        )
    db.dispose()
    admin_login(page, server, "/dashboard")
    page.locator('#participants tr[data-participant]:has-text("PIDDOUBT")').click()
    item = page.locator('#detail .bonuses li[data-state="in_doubt"]')
    expect(item).to_contain_text("in doubt: neither paid nor unpaid until settled")
    expect(item.locator(".bonus-note")).to_contain_text(
        "settled from Prolific's record of the submission's bonuses"
    )
    item.locator('[data-action="settle-bonus"]').click()
    expect(item.locator(".form-error")).to_contain_text("is in doubt", timeout=WAIT_MS)
    (row,) = server.query("SELECT state FROM bonuses WHERE unique_token = 'doubt-token-1'")
    assert row.state == "in_doubt"
