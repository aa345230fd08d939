"""The teaching page in small windows: usable at 1024x640 (the grid large, Next agent in view
without scrolling) and readable at 800x600."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from playwright.sync_api import Page, expect

from tests.browser.conftest import (
    WAIT_MS,
    LiveServer,
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
    page: Page, server: LiveServer, width: int, height: int, grid_width: int, font_px: float
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
    # Labels on the grid stay readable: their rendered size on screen.
    smallest = page.evaluate(
        """() => Math.min(...[...document.querySelectorAll('.board svg.grid text')]
             .map((t) => t.getBoundingClientRect().height).filter((h) => h > 0))"""
    )
    print(f"{width}x{height}: smallest label {smallest:.1f} px")
    assert smallest >= font_px
    page.screenshot(path=f"/tmp/sq-shots/{width}x{height}.png")
