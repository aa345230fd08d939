""" "Stop and delete my data" on the study page: below every page once the participant is known,
reached and used by keyboard alone (Tab, Enter, Escape), one confirmation in a modal dialog that
the teaching keys do not reach, no axe-core violation with the dialog shut or open; afterwards
nothing of the participant is left in the database but the audit row."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from playwright.sync_api import Browser, Page, expect

from tests.browser.conftest import (
    LiveServer,
    axe_violations,
    domain_toml,
    run_live_server,
    study_toml,
)

pytestmark = pytest.mark.browser
MOST_TABS = 60  # more than every control of the teaching page


@pytest.fixture(scope="module")
def lab_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    config = study_toml(
        mode="lab",
        domains_toml=domain_toml("navigation", "wall"),
        learners='["cloning"]',
        agents=1,
        allow_anonymous=True,
        tutorial=False,
    )
    yield from run_live_server(Path(tmp_path_factory.mktemp("withdrawal")), config)


def new_page(browser: Browser, context_args: dict[str, Any]) -> Page:
    return browser.new_context(**context_args).new_page()


def tab_to(page: Page, selector: str) -> None:
    """Press Tab until ``selector`` has the focus (a keyboard user's way there)."""
    for _ in range(MOST_TABS):
        if page.evaluate("(s) => document.activeElement?.matches(s) ?? false", selector):
            return
        page.keyboard.press("Tab")
    raise AssertionError(f"{selector} cannot be reached with Tab")


def focused(page: Page) -> str | None:
    return page.evaluate("() => document.activeElement?.dataset.action ?? null")


def test_a_participant_withdraws_by_keyboard_and_is_erased(
    browser: Browser, browser_context_args: dict[str, Any], lab_server: LiveServer
) -> None:
    page = new_page(browser, browser_context_args)
    try:
        page.goto(f"{lab_server.url}/study")
        withdraw = page.locator('[data-action="withdraw"]')
        expect(withdraw).to_be_visible()
        assert axe_violations(page) == []  # the consent page with the control below it
        page.click('[data-action="agree"]')
        page.click('[data-action="start"]')
        expect(page.locator(".task").first).to_be_visible()
        (participant,) = lab_server.query("SELECT id FROM participants")
        mode_before = lab_server.query("SELECT mode FROM learning_sessions")

        # Keyboard only: to the control, open the dialog, back out with Escape.
        tab_to(page, '[data-action="withdraw"]')
        page.keyboard.press("Enter")
        dialog = page.locator("dialog.withdraw-dialog")
        expect(dialog).to_be_visible()
        assert focused(page) == "withdraw-keep"
        assert axe_violations(page) == []  # the dialog open
        page.keyboard.press("d")  # a teaching key: the dialog keeps it from the agent
        page.keyboard.press("Escape")
        expect(dialog).to_be_hidden()
        assert focused(page) == "withdraw"
        assert lab_server.query("SELECT mode FROM learning_sessions") == mode_before
        assert lab_server.query("SELECT count(*) FROM participants") == [(1,)]

        # Open it again and confirm: one confirmation.
        page.keyboard.press("Enter")
        expect(dialog).to_be_visible()
        page.keyboard.press("Tab")
        assert focused(page) == "withdraw-confirm"
        page.keyboard.press("Enter")
        expect(page.locator("h1")).to_have_text("Your data has been deleted")
        expect(page.locator("[data-withdrawn]")).to_have_attribute("data-withdrawn", "lab")
        expect(withdraw).to_be_hidden()
        assert axe_violations(page) == []

        for table in (
            "participants",
            "learning_sessions",
            "events",
            "episodes",
            "learner_updates",
            "status_changes",
        ):
            assert lab_server.query(f"SELECT count(*) FROM {table}") == [(0,)], table
        assert lab_server.query("SELECT participant_id, erased_by FROM erasures") == [
            (participant[0], "participant")
        ]
        # The page is a new visitor's now: reloading starts over, as a new participant.
        page.reload()
        expect(page.locator('[data-action="agree"]')).to_be_visible()
    finally:
        page.context.close()
