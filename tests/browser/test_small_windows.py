"""The participant's pages in small windows: at 1024x640 the consent page's answers are in view
and its text can be scrolled by keyboard, the teaching page (the grid large, Next agent in view)
needs no scrolling, nor does its panel at any step of the tutorial; at 800x600 it stays
readable."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from playwright.sync_api import Page, Route, expect

from tests.browser.conftest import (
    WAIT_MS,
    LiveServer,
    Study,
    domain_toml,
    run_live_server,
    study_toml,
)

pytestmark = pytest.mark.browser


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    config = study_toml(
        mode="lab",
        domains_toml=domain_toml("navigation", "two-rooms"),
        learners='["cloning"]',
        agents=1,
    )
    yield from run_live_server(tmp_path_factory.mktemp("small-windows"), config)


def in_view(page: Page, selector: str) -> bool:
    """The element is wholly inside the window and not hidden by a scrolling parent."""
    return bool(
        page.evaluate(
            """(selector) => {
              const element = document.querySelector(selector);
              const box = element.getBoundingClientRect();
              const inside = (a, b) => a.top >= b.top - 1 && a.left >= b.left - 1 && a.bottom <= b.bottom + 1 && a.right <= b.right + 1;
              if (!inside(box, { top: 0, left: 0, bottom: innerHeight, right: innerWidth })) return false;
              for (let parent = element.parentElement; parent; parent = parent.parentElement) {
                const outer = parent.getBoundingClientRect();
                const style = getComputedStyle(parent);
                if (style.overflow !== "visible" && !inside(box, outer)) return false;
              }
              return true;
            }""",
            selector,
        )
    )


@pytest.mark.parametrize(
    ("width", "height", "grid_width", "font_px"),
    [(1024, 640, 520, 11.5), (800, 600, 440, 9.5)],
)
def test_the_teaching_page_fits_a_small_window(
    page: Page,
    server: LiveServer,
    tmp_path: Path,
    width: int,
    height: int,
    grid_width: int,
    font_px: float,
) -> None:
    page.set_viewport_size({"width": width, "height": height})
    page.goto(f"{server.url}/study")
    page.click('[data-action="agree"]')
    page.click('[data-action="start"]')
    expect(page.locator(".teach-page")).to_be_visible(timeout=WAIT_MS)
    page.wait_for_timeout(300)  # the grid is fitted to its frame after layout
    grid = page.locator(".board svg.grid").bounding_box()
    assert grid is not None
    print(f"{width}x{height}: grid {grid['width']:.0f}x{grid['height']:.0f}")
    assert grid["width"] >= grid_width
    assert in_view(page, ".board svg.grid")
    assert in_view(page, '[data-action="next"]')
    assert in_view(page, ".status")
    # A task's name and its count each on one line, with the longest a study shows.
    lines = page.eval_on_selector_all(
        ".task-list button.task",
        """(buttons) => buttons.map((b) => {
             b.querySelector('.task-name').textContent = 'Crops field';
             b.querySelector('.task-count').textContent = '✓ 128 moves shown';
             return ['.task-name', '.task-count'].map((part) => {
               const range = document.createRange();
               range.selectNodeContents(b.querySelector(part));
               return new Set([...range.getClientRects()].map((r) => Math.round(r.top))).size;
             }); })""",
    )
    assert lines and all(each == [1, 1] for each in lines), lines
    assert in_view(page, '[data-action="next"]')
    # Labels on the grid stay readable: their rendered size on screen.
    smallest = page.evaluate(
        """() => Math.min(...[...document.querySelectorAll('.board svg.grid text')]
             .map((t) => t.getBoundingClientRect().height).filter((h) => h > 0))"""
    )
    print(f"{width}x{height}: smallest label {smallest:.1f} px")
    assert smallest >= font_px
    page.screenshot(path=str(tmp_path / f"{width}x{height}.png"))


def panel_overflow(page: Page) -> int:
    """How much taller the teaching panel's content is than the panel (scrolled inside)."""
    return int(
        page.evaluate(
            "() => { const p = document.querySelector('.panel');"
            " return p.scrollHeight - p.clientHeight; }"
        )
    )


@pytest.mark.parametrize(("width", "height"), [(1024, 640), (1280, 720)])
def test_the_consent_page_fits_and_its_text_scrolls_by_keyboard(
    page: Page, server: LiveServer, width: int, height: int
) -> None:
    page.set_viewport_size({"width": width, "height": height})

    # A consent text longer than the box: the box scrolls, the answers stay in view.
    def longer_consent(route: Route) -> None:
        response = route.fetch()
        sentence = "We record what you do in the interface."
        route.fulfill(response=response, body=response.text().replace(sentence, sentence * 60))

    page.route("**/study", longer_consent)
    page.goto(f"{server.url}/study")
    text = page.locator(".consent-text")
    expect(text).to_be_visible()
    assert in_view(page, '[data-action="agree"]')
    assert in_view(page, '[data-action="decline"]')
    # A named region in the tab order, which the arrow keys scroll.
    expect(text).to_have_attribute("tabindex", "0")
    expect(text).to_have_attribute("role", "region")
    expect(text).to_have_accessible_name("Consent to take part")
    assert text.evaluate("(box) => box.scrollHeight > box.clientHeight")
    page.keyboard.press("Tab")
    expect(text).to_be_focused()
    page.keyboard.press("PageDown")
    page.wait_for_function(
        "() => document.querySelector('.consent-text').scrollTop > 0", timeout=5000
    )


def test_the_tutorial_s_panel_needs_no_scrolling_at_1024x640(
    page: Page, server: LiveServer
) -> None:
    page.set_viewport_size({"width": 1024, "height": 640})
    page.goto(f"{server.url}/study")
    page.click('[data-action="agree"]')
    page.click('[data-action="start"]')
    study = Study(page)
    expect(study.teach).to_have_attribute("data-kind", "tutorial", timeout=WAIT_MS)
    scrolling: list[tuple[str, int]] = []

    def check(step: str) -> None:
        page.wait_for_timeout(100)  # the card's text is laid out
        overflow = panel_overflow(page)
        if overflow > 1:
            scrolling.append((step, overflow))

    study.do_tutorial(on_step=check)
    check("study")
    assert scrolling == []
    assert in_view(page, '[data-action="next"]')
