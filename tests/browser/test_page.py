"""The participant's page on its own (a lab study, no platform): declining consent, arrow keys
that never scroll, the gravity domain drawn with its colours but not their directions, and a
reload that continues where the participant was."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from playwright.sync_api import Page, expect

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

GRAVITY = domain_toml("gravity", "choices")


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    config = study_toml(
        mode="lab", domains_toml=GRAVITY, learners='["cloning"]', agents=1, allow_anonymous=True
    )
    yield from run_live_server(tmp_path_factory.mktemp("lab-study"), config)


def arrive(page: Page, server: LiveServer) -> Study:
    page.goto(f"{server.url}/study")
    expect(page.locator('[data-action="agree"]')).to_be_visible()
    return Study(page)


def test_declining_consent_ends_politely_and_is_recorded(page: Page, server: LiveServer) -> None:
    watch = Watch(server.url).attach(page)
    arrive(page, server)
    page.click('[data-action="decline"]')
    expect(page.locator("h1")).to_have_text("Thank you")
    page.reload()
    expect(page.locator("h1")).to_have_text("Thank you")
    participant = page.request.get(f"{server.url}/api/participant").json()
    (row,) = server.query(
        "SELECT status FROM participants WHERE id = :p", p=participant["participant_id"]
    )
    assert row.status == "declined"
    watch.check()


def test_arrow_keys_move_the_agent_and_never_scroll(page: Page, server: LiveServer) -> None:
    watch = Watch(server.url).attach(page)
    study = arrive(page, server)
    page.click('[data-action="agree"]')
    page.click('[data-action="start"]')
    expect(study.teach).to_be_visible()
    # A page taller than the window, which the arrow keys would scroll by default.
    page.evaluate("document.body.style.minHeight = '4000px'")
    assert page.evaluate("document.documentElement.scrollHeight > 2 * window.innerHeight")
    study.focus()
    moves = 0
    for key in ("ArrowDown", "ArrowDown", "ArrowRight", "ArrowUp", "ArrowLeft", "ArrowDown"):
        before = study.seq()
        study.press(key)
        study.answered(before)
        moves += 1
        assert page.evaluate("window.scrollY") == 0
    # Also with the focus on a button (where Chrome scrolls too).
    page.focus('[data-action="reset"]')
    before = study.seq()
    study.press("ArrowDown")
    study.answered(before)
    assert page.evaluate("window.scrollY") == 0
    # The moves were idle moves (transitions), stored, and none was a demonstration.
    participant = page.request.get(f"{server.url}/api/participant").json()
    rows = server.query(
        "SELECT record FROM events WHERE participant_id = :p AND kind = 'move'",
        p=participant["participant_id"],
    )
    assert len(rows) == moves + 1 and {row.record for row in rows} == {"transition"}
    watch.check()


def test_the_gravity_domain_hides_directions_and_a_reload_continues(
    page: Page, server: LiveServer, screenshot_dir: Path
) -> None:
    watch = Watch(server.url).attach(page)
    study = arrive(page, server)
    page.screenshot(path=str(screenshot_dir / "consent.png"))
    page.click('[data-action="agree"]')
    expect(page.locator('[data-action="start"]')).to_be_visible()
    page.screenshot(path=str(screenshot_dir / "instructions.png"))
    page.click('[data-action="start"]')
    expect(study.teach).to_have_attribute("data-environment", "gravity-tutorial")
    study.do_tutorial(screenshot=screenshot_dir / "tutorial-gravity.png")
    expect(study.teach).to_have_attribute("data-environment", "choices")
    # Coloured cells with their letters; the agent shows its gravity; no colour's direction.
    cells = page.locator("g.gravity-cell")
    expect(cells).to_have_count(4)
    expect(cells.first.locator("text")).to_have_text("G")
    feature = str(page.locator("g.agent").get_attribute("data-feature"))
    assert feature in ("north", "south", "east", "west")
    expect(page.locator(".agent-feature")).to_contain_text(f"Gravity {feature}")
    view = page.request.get(f"{server.url}/api/sessions/{study.session}").json()
    assert "gravity_of_colour" not in view["environment"]
    # A demonstration, a reload in the middle of the next one, and it goes on from there.
    study.demonstrate(0)
    study.demonstrate(1, reload_after=2)
    study.select_task(0)
    page.screenshot(path=str(screenshot_dir / "teaching-gravity.png"))
    expect(page.locator('[data-action="next"]')).to_be_enabled()
    study.let_agent_try_with_feedback()
    study.press("n")
    page.locator('[data-action="confirm-next"]').click()
    code = page.locator('[data-testid="completion-code"]')
    expect(code).to_be_visible(timeout=WAIT_MS)
    participant = page.request.get(f"{server.url}/api/participant").json()
    (row,) = server.query(
        "SELECT completion_code FROM participants WHERE id = :p",
        p=participant["participant_id"],
    )
    assert code.inner_text() == row.completion_code
    # A refresh shows the same code again.
    page.reload()
    expect(page.locator('[data-testid="completion-code"]')).to_have_text(row.completion_code)
    watch.check()
    # The gravity pages are in the screenshot folder (BAM_SCREENSHOT_DIR: the docs' pictures).
    for name in ("tutorial-gravity.png", "teaching-gravity.png", "consent.png"):
        path = screenshot_dir / name
        assert path.is_file() and path.stat().st_size > 10_000, path
