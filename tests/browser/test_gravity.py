"""The study setting ``reveal_gravity``: on, the gravity cells show the direction they set (an
arrow on each cell, and the direction in the legend); off (the default), the direction is
nowhere in the page's DOM nor in the environment the API describes to the page."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from playwright.sync_api import Page, expect

from server import domains
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
DIRECTIONS = ("north", "south", "east", "west")
ANGLE = {"north": 0, "east": 90, "south": 180, "west": 270}


@pytest.fixture(scope="module", params=[False, True], ids=["hidden", "revealed"])
def server(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[LiveServer]:
    config = study_toml(
        mode="lab",
        domains_toml=GRAVITY,
        learners='["cloning"]',
        agents=1,
        allow_anonymous=True,
        reveal_gravity=request.param,
    )
    yield from run_live_server(tmp_path_factory.mktemp("gravity-study"), config)


def test_gravity_directions_are_shown_only_when_the_study_reveals_them(
    page: Page, server: LiveServer, request: pytest.FixtureRequest
) -> None:
    reveal = bool(request.node.callspec.params["server"])
    watch = Watch(server.url).attach(page)
    page.goto(f"{server.url}/study")
    page.click('[data-action="agree"]')
    page.click('[data-action="start"]')
    study = Study(page)
    expect(study.teach).to_have_attribute("data-environment", "gravity-tutorial", timeout=WAIT_MS)
    env = domains.make("gravity-tutorial")
    mapping: dict[str, str] = env.layout["gravity_of_colour"]
    colours = {cell["colour"] for cell in env.describe()["colours"]}
    assert len(colours) >= 2 and len(set(mapping.values())) >= 2

    view = page.request.get(f"{server.url}/api/sessions/{study.session}").json()
    legend = page.locator(".legend li").filter(has_text="cell (")
    expect(legend).to_have_count(len(colours))
    cells = page.locator("g.gravity-cell")
    expect(cells).to_have_count(len(env.describe()["colours"]))
    if reveal:
        assert view["environment"]["gravity_of_colour"] == mapping
        for colour in colours:
            coloured = page.locator(f"g.gravity-cell.gravity-{colour}")
            for index in range(coloured.count()):
                cell = coloured.nth(index)
                expect(cell).to_have_attribute("data-direction", mapping[colour])
                # The arrow points the colour's way; no letter stands in for it.
                arrow = cell.locator("g")
                expect(arrow).to_have_count(1)
                assert f"rotate({ANGLE[mapping[colour]]} 50 50)" in str(
                    arrow.get_attribute("transform")
                )
                expect(cell.locator("text")).to_have_count(0)
            expect(legend.filter(has_text=colour.capitalize())).to_contain_text(
                f"sets the gravity {mapping[colour]}"
            )
        expect(page.locator(".rules")).to_contain_text("the direction its arrow shows")
    else:
        assert "gravity_of_colour" not in view["environment"]
        assert not page.evaluate(
            "JSON.parse(document.getElementById('study-data').textContent).reveal_gravity"
        )
        # Each cell has its colour's letter, no arrow, and no direction anywhere in it.
        for index in range(cells.count()):
            cell = cells.nth(index)
            assert cell.get_attribute("data-direction") is None
            expect(cell.locator("g")).to_have_count(0)
            expect(cell.locator("text")).to_have_count(1)
            markup = cell.evaluate("node => node.outerHTML").lower()
            assert not any(direction in markup for direction in DIRECTIONS), markup
        for index in range(legend.count()):
            text = legend.nth(index).inner_text().lower()
            assert "sets the gravity" in text
            assert not any(direction in text for direction in DIRECTIONS), text
        expect(page.locator(".rules")).to_contain_text("for you to find out by trying")
        # The whole page holds no word of which colour sets which direction: the only
        # directions in it are the agent's own gravity and the general rule.
        html = page.content().lower()
        for colour, direction in mapping.items():
            assert f"{colour} cell: sets the gravity {direction}" not in html
            assert f"sets the gravity {direction}" not in html
    watch.check()
