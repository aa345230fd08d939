"""A study with a post-study questionnaire (the questions of
``server/examples/questionnaire-study.toml``): after the last agent the participant answers it
with the keyboard alone, is told what is missing, and then sees the completion code. axe-core
checks the page, with and without its error messages, as tests/browser/test_accessibility.py
checks every other page."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import pytest
from playwright.sync_api import Page, expect

from tests.browser.conftest import (
    WAIT_MS,
    LiveServer,
    Study,
    Watch,
    axe_violations,
    domain_toml,
    run_live_server,
    study_toml,
)

pytestmark = pytest.mark.browser

EXAMPLE = Path(__file__).resolve().parents[2] / "server" / "examples" / "questionnaire-study.toml"


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    text = EXAMPLE.read_text(encoding="utf-8")
    questionnaire = text[text.index("[questionnaire]") :]
    config = study_toml(
        mode="lab",
        domains_toml=domain_toml("navigation", "wall"),
        learners='["cloning"]',
        agents=1,
        allow_anonymous=True,
        tutorial=False,
    )
    yield from run_live_server(
        tmp_path_factory.mktemp("questionnaire-study"), config + "\n" + questionnaire
    )


def test_the_questionnaire_is_answered_by_keyboard_before_the_code(
    page: Page, server: LiveServer, screenshot_dir: Path
) -> None:
    watch = Watch(server.url).attach(page)
    page.goto(f"{server.url}/study")
    study = Study(page)
    page.click('[data-action="agree"]')
    page.click('[data-action="start"]')
    expect(study.teach).to_be_visible(timeout=WAIT_MS)
    study.focus()
    for task in range(page.locator(".task").count()):
        study.demonstrate(task)
    study.press("n")
    page.locator('[data-action="confirm-next"]').click()

    heading = page.get_by_role("heading", name="A few questions")
    expect(heading).to_be_visible(timeout=WAIT_MS)
    expect(heading).to_be_focused()
    difficulty = page.get_by_role("group", name=re.compile("How easy was it"))
    best = page.get_by_role("group", name=re.compile("Which agent learned best"))
    comments = page.get_by_label(re.compile("Anything else"))
    expect(difficulty).to_be_visible()
    expect(page.get_by_label("Neither easy nor hard")).to_have_attribute("type", "radio")
    expect(page.locator('[data-testid="completion-code"]')).to_have_count(0)
    assert axe_violations(page) == []  # WCAG 2.0/2.1 A and AA, as every other page

    # Tab into the scale and pick its fourth point with the arrow keys, then Tab past the
    # other questions to the button and send: the missing answer is named and focused.
    study.press("Tab")
    expect(page.get_by_label("Very hard")).to_be_focused()
    for _ in range(3):
        study.press("ArrowRight")
    expect(page.get_by_label("Easy", exact=True)).to_be_checked()
    for _ in range(3):
        study.press("Tab")
    expect(page.locator('[data-action="submit-questionnaire"]')).to_be_focused()
    study.press("Enter")
    expect(page.get_by_role("alert")).to_have_text("One question still needs an answer.")
    expect(best.get_by_label("The first agent")).to_be_focused()
    expect(best.get_by_role("radio").first).to_have_attribute("aria-invalid", "true")
    assert axe_violations(page) == []  # the page with its error messages
    study.press("ArrowDown")
    expect(best.get_by_label("The second agent")).to_be_checked()
    study.press("Tab")
    expect(comments).to_be_focused()
    page.keyboard.type("Showing each goal once was enough.")
    page.screenshot(path=str(screenshot_dir / "questionnaire.png"), full_page=True)
    study.press("Tab")
    study.press("Enter")

    code = page.locator('[data-testid="completion-code"]')
    expect(code).to_have_text(re.compile(r"^[A-Z0-9]{10}$"), timeout=WAIT_MS)
    rows = server.query("SELECT question_id, answer, label FROM questionnaire_answers ORDER BY id")
    assert [tuple(row) for row in rows] == [
        ("difficulty", "4", "Easy"),
        ("best_agent", "The second agent", None),
        ("comments", "Showing each goal once was enough.", None),
    ]
    (participant,) = server.query("SELECT status, completion_code FROM participants")
    assert participant.status == "completed"
    assert participant.completion_code == code.text_content()
    # A reload shows the code again, not the questionnaire.
    page.reload()
    expect(page.locator('[data-testid="completion-code"]')).to_have_text(
        participant.completion_code, timeout=WAIT_MS
    )
    watch.check()
