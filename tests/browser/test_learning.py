"""The "learning" indicator is quiet: while a learner update is pending the participant goes on
demonstrating, and every move is accepted and drawn, with nothing over the grid.

The test's server runs learner updates in a thread that holds each update (not the first, which
builds the untrained learner) until the test lets it go, so that "pending" lasts as long as the
test needs instead of depending on how fast the machine is."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import pytest
from playwright.sync_api import Page, expect

from tests.browser.conftest import (
    WAIT_MS,
    LiveServer,
    Study,
    Watch,
    domain_toml,
    next_state,
    run_live_server,
    shortest_path,
    study_toml,
)

pytestmark = pytest.mark.browser

NAVIGATION = domain_toml("navigation", "wall")


class HeldUpdates(ThreadPoolExecutor):
    """Runs learner updates in a thread; an update that fits the learner waits for ``release``."""

    def __init__(self) -> None:
        super().__init__(max_workers=1, thread_name_prefix="held-update")
        self.release = threading.Event()
        self.held = 0

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future[Any]:
        job = args[0] if args else None
        if not (isinstance(job, dict) and job.get("fit")):
            return super().submit(fn, *args, **kwargs)
        self.held += 1

        def held() -> Any:
            self.release.wait()
            return fn(*args, **kwargs)

        return super().submit(held)


@pytest.fixture(scope="module")
def updates() -> Iterator[HeldUpdates]:
    executor = HeldUpdates()
    yield executor
    executor.release.set()
    executor.shutdown(wait=True, cancel_futures=True)


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory, updates: HeldUpdates) -> Iterator[LiveServer]:
    config = study_toml(
        mode="lab",
        domains_toml=NAVIGATION,
        learners='["cloning"]',
        agents=1,
        allow_anonymous=True,
        tutorial=False,
    )
    yield from run_live_server(tmp_path_factory.mktemp("learning-study"), config, updates)


def nothing_over_the_agent(page: Page) -> None:
    """The element at the agent's place is the grid's own drawing, not something covering it."""
    box = page.locator("g.agent").bounding_box()
    assert box is not None
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    assert page.evaluate(
        "([x, y]) => Boolean(document.elementFromPoint(x, y)?.closest('.board svg'))", [x, y]
    )
    expect(page.locator(".offline")).to_be_hidden()
    expect(page.locator("dialog.confirm")).not_to_have_attribute("open", "")


def test_demonstrating_goes_on_while_the_agent_learns(
    page: Page, server: LiveServer, updates: HeldUpdates
) -> None:
    watch = Watch(server.url).attach(page)
    page.goto(f"{server.url}/study")
    page.click('[data-action="agree"]')
    page.click('[data-action="start"]')
    study = Study(page)
    expect(study.teach).to_have_attribute("data-kind", "study", timeout=WAIT_MS)
    indicator = page.locator(".learning")
    study.wait_for("pending", 0)  # the untrained learner is built
    expect(indicator).to_be_hidden()
    study.focus()

    # A demonstration to the goal queues an update, which the server holds: the agent learns.
    study.demonstrate(0)
    study.wait_for("pending", 1)
    expect(indicator).to_be_visible()
    expect(indicator).to_contain_text("you can go on teaching")
    assert updates.held == 1

    # Demonstrating goes on meanwhile: each move is accepted and drawn, the indicator stays.
    study.select_task(1)
    study.key_and_wait("r")
    study.keep_away_from_goal(1, 2)
    study.press("d")
    study.wait_for("mode", "demonstrate")
    path = shortest_path(study.environment, study.state(), 1)
    for moves, action in enumerate(path, start=1):
        expected = next_state(study.environment, study.state(), action)
        study.move(action)
        agent = page.locator("g.agent")
        row, column = (
            int(str(agent.get_attribute("data-row"))),
            int(str(agent.get_attribute("data-column"))),
        )
        assert f"translate({column * 100}px, {row * 100}px)" in str(agent.get_attribute("style"))
        assert study.state() == expected
        if moves < len(path):
            study.wait_for("episode-actions", moves)
            expect(indicator).to_be_visible()
            nothing_over_the_agent(page)
    # The second demonstration reached its goal too, and queued a second update.
    study.wait_for("mode", "idle")
    expect(page.locator('.task[data-task="1"]')).to_have_attribute("data-count", str(len(path)))
    study.wait_for("pending", 2)
    expect(indicator).to_be_visible()
    nothing_over_the_agent(page)
    expect(page.locator('[data-action="next"]')).to_be_enabled()
    rows = server.query(
        "SELECT COUNT(*) AS n FROM events"
        " WHERE session_id = :s AND record = 'demonstration' AND task = 1",
        s=study.session,
    )
    assert rows[0].n == len(path)  # every move was stored as demonstrated

    # Once the updates are let go, the indicator goes away by itself.
    updates.release.set()
    study.wait_for("pending", 0)
    expect(indicator).to_be_hidden()
    watch.check()
