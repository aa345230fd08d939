"""The experimenter reviews a worker's submitted HIT from the dashboard: approves it with
feedback and pays a bonus; the local MTurk replica's HIT page shows both."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from playwright.sync_api import Page, expect

from tests.browser.conftest import (
    WAIT_MS,
    LiveServer,
    Watch,
    admin_login,
    domain_toml,
    run_live_server,
    study_frame,
    study_toml,
)
from tests.browser.test_submit_target import complete_over_the_api

pytestmark = pytest.mark.browser


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    config = study_toml(
        mode="mturk",
        domains_toml=domain_toml("navigation", "wall"),
        learners='["cloning"]',
        agents=1,
        tutorial=False,
    )
    yield from run_live_server(tmp_path_factory.mktemp("review-study"), config)


def test_approve_and_pay_a_bonus_from_the_dashboard(page: Page, server: LiveServer) -> None:
    watch = Watch(server.url).attach(page)
    admin_login(page, server, "/mturk")
    page.fill("#workerId", "WREVIEW")
    page.click('[data-action="accept"]')
    page.wait_for_url(f"{server.url}/mturk/work/*")
    study_frame(page)
    token = next(c["value"] for c in page.context.cookies() if c["name"] == "bam_participant")
    complete_over_the_api(server, token)
    page.reload()
    frame = study_frame(page)
    frame.locator('[data-action="submit-hit"]').click(timeout=WAIT_MS)
    page.wait_for_url(f"{server.url}/mturk/externalSubmit")

    page.goto(f"{server.url}/dashboard")
    page.locator("#participants tr[data-participant]").click()
    detail = page.locator("#detail")
    # A rejection without feedback is stopped on the page.
    detail.locator('[data-action="reject"]').click()
    expect(detail.locator(".review .form-error")).to_have_text(
        "A rejection needs feedback: the participant is shown why."
    )
    page.get_by_label("Feedback to the worker (needed to reject)").fill("Thank you!")
    # Approve and Pay ask first: declined, nothing is sent; accepted, it goes.
    asked: list[str] = []
    page.once("dialog", lambda dialog: (asked.append(dialog.message), dialog.dismiss()))
    detail.locator('[data-action="approve"]').click()
    expect(detail.locator('[data-action="approve"]')).to_be_enabled()
    assert server.query("SELECT id FROM assignment_reviews") == []
    page.on("dialog", lambda dialog: (asked.append(dialog.message), dialog.accept()))
    detail.locator('[data-action="approve"]').click()
    expect(detail.locator('[data-review="approved"]')).to_contain_text("Thank you!")
    expect(detail.locator('[data-action="approve"]')).to_have_count(0)
    page.get_by_label("Bonus (USD)").fill("1.25")
    page.get_by_label("Reason, shown to the participant").fill("Taught every task")
    detail.locator('[data-action="bonus"]').click()
    expect(detail.locator('.bonuses li[data-amount="1.25"]')).to_contain_text("Taught every task")

    (review,) = server.query("SELECT decision, feedback, backend FROM assignment_reviews")
    assert tuple(review) == ("approved", "Thank you!", "mturk-replica")
    assert [m.split("?")[0] for m in asked] == [
        "Approve this submission",
        "Approve this submission",
        "Pay a bonus of 1.25",
    ]
    (bonus,) = server.query("SELECT amount_cents, reason FROM bonuses")
    assert tuple(bonus) == (125, "Taught every task")

    page.goto(f"{server.url}/mturk")
    row = page.locator('#assignments tr[data-worker="WREVIEW"]')
    expect(row).to_have_attribute("data-status", "approved")
    expect(row).to_contain_text("Thank you!")
    expect(page.locator('#bonuses tr[data-amount="1.25"]')).to_contain_text("Taught every task")
    watch.check()
