""" "Stop and delete my data" on the study page: below every page once the participant is known,
reached and used by keyboard alone (Tab, Enter, Escape), one confirmation in a modal dialog that
the teaching keys do not reach, no axe-core violation with the dialog shut or open; afterwards
nothing of the participant is left in the database but the audit row. A Prolific participant's
page says what happened and what to do on Prolific, and the replica's page agrees."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from playwright.sync_api import Browser, Page, expect

from server.app.platforms.prolific import NO_CONSENT_REASON
from tests.app.platforms.test_prolific import draft
from tests.browser.conftest import (
    ADMIN_TOKEN,
    LiveServer,
    admin_login,
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


@pytest.fixture(scope="module")
def prolific_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    config = study_toml(
        mode="prolific", domains_toml=domain_toml("navigation", "wall"), learners='["cloning"]'
    ).replace(
        'mode = "prolific"',
        'mode = "prolific"\nprolific_code = "C1A2B3C4"\nprolific_no_consent_code = "NOCONSNT"',
    )
    yield from run_live_server(Path(tmp_path_factory.mktemp("prolific-withdrawal")), config)


def replica_study(server: LiveServer) -> str:
    """A published study of the server's Prolific replica, made as `prolific create` makes it
    (its NO_CONSENT code asks for a return with our reason)."""
    made = draft(2)
    made["external_study_url"] = (
        f"{server.url}/study?PROLIFIC_PID={{{{%PROLIFIC_PID%}}}}&STUDY_ID={{{{%STUDY_ID%}}}}"
        "&SESSION_ID={{%SESSION_ID%}}"
    )
    for code in made["completion_codes"]:
        if code["code_type"] == "NO_CONSENT":
            code["actions"] = [{"action": "REQUEST_RETURN", "return_reason": NO_CONSENT_REASON}]
    token = {"Authorization": f"Token {ADMIN_TOKEN}"}
    with httpx.Client(base_url=server.url, headers=token, timeout=60) as http:
        study = str(http.post("/prolific/api/v1/studies/", json=made).json()["id"])
        published = http.post(
            f"/prolific/api/v1/studies/{study}/transition/", json={"action": "PUBLISH"}
        )
        assert published.status_code == 200, published.text
    return study


def test_a_prolific_participant_who_withdraws_is_told_what_happened_and_how_to_return(
    browser: Browser, browser_context_args: dict[str, Any], prolific_server: LiveServer
) -> None:
    """On the replica: the study page says the data is deleted and what to do on Prolific, and
    sends nobody away by itself; its button takes the NO_CONSENT code to the replica, which
    keeps the submission (as Prolific does), completes it with a return requested and says so
    with the reason and a Return button; Return ends it as RETURNED."""
    server = prolific_server
    study = replica_study(server)
    page = new_page(browser, browser_context_args)
    try:
        admin_login(page, server, "/prolific")
        page.locator(f'[data-study="{study}"] form[action$="/take-part"] button').click()
        page.wait_for_url(f"{server.url}/study?**")
        page.click('[data-action="agree"]')
        page.click('[data-action="start"]')
        expect(page.locator(".task").first).to_be_visible()
        (submission,) = server.query("SELECT id FROM prolific_replica_submissions")

        page.click('[data-action="withdraw"]')
        page.click('[data-action="withdraw-confirm"]')
        expect(page.locator("h1")).to_have_text("Your data has been deleted")
        said = page.locator('[data-withdrawn="prolific"]')
        expect(said).to_contain_text("Your data has been deleted")
        expect(said).to_contain_text("\u201cReturn\u201d")
        back = page.locator('[data-action="leave-platform"]')
        expect(back).to_have_text("Back to Prolific")
        assert axe_violations(page) == []
        page.wait_for_timeout(1000)
        assert page.url.startswith(f"{server.url}/study")  # still here: nothing redirected
        assert server.query("SELECT count(*) FROM participants") == [(0,)]
        # Prolific's record stays: the submission is still the participant's, still active.
        assert server.query("SELECT id, status FROM prolific_replica_submissions") == [
            (submission.id, "ACTIVE")
        ]

        back.click()
        page.wait_for_url(f"{server.url}/prolific/submissions/complete?cc=NOCONSNT")
        expect(page.locator("h1")).to_have_text("Return requested")
        expect(page.locator("main p").first).to_contain_text(NO_CONSENT_REASON)
        assert axe_violations(page) == []
        (row,) = server.query("SELECT status, return_requested FROM prolific_replica_submissions")
        assert row.status == "AWAITING REVIEW" and row.return_requested is not None

        page.click('[data-action="return"]')
        page.wait_for_url(f"{server.url}/prolific")
        expect(page.locator(f'tr[data-submission="{submission.id}"]')).to_have_attribute(
            "data-status", "RETURNED"
        )
        assert server.query("SELECT count(*) FROM participants") == [(0,)]
    finally:
        page.context.close()
