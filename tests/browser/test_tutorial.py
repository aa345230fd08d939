"""The tutorial advances only when the participant has done what its step asks: part of a step
(one move of three, a demonstration stopped before the goal or cut short by switching task)
leaves the step where it is and "Finish the tutorial" disabled. Letting the agent try from the
goal starts it from a random start, with no episode for the goal itself."""

from __future__ import annotations

import re
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
    next_state,
    run_live_server,
    study_toml,
)

pytestmark = pytest.mark.browser

NAVIGATION = domain_toml("navigation", "wall")


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    config = study_toml(
        mode="lab", domains_toml=NAVIGATION, learners='["cloning"]', agents=1, allow_anonymous=True
    )
    yield from run_live_server(tmp_path_factory.mktemp("tutorial-study"), config)


class Tutorial:
    def __init__(self, page: Page) -> None:
        self.page = page
        self.card = page.locator(".tutorial-card")
        self.next = page.locator('[data-action="next"]')

    def at(self, step: str) -> None:
        expect(self.card).to_have_attribute("data-step", step, timeout=WAIT_MS)

    def stays_at(self, step: str) -> None:
        """The page has answered and shown what the last key did: the step has not moved."""
        self.at(step)
        expect(self.next).to_be_disabled()


def stop_demonstration_early(study: Study, task: int, how: str) -> None:
    """Demonstrate ``task`` for one move, then end it before its goal: with Stop (S), or by
    selecting the other task."""
    study.keep_away_from_goal(task, 3)
    study.press("d")
    study.wait_for("mode", "demonstrate")
    episodes = int(study.data("episodes"))
    assert study.walk_to_goal(task, limit=1) == 1
    if how == "stop":
        study.press("s")
        study.wait_for("mode", "idle")
    else:
        other = 1 - task
        study.press(str(other + 1))
        study.wait_for("task", other)
        study.press("s")
        study.wait_for("mode", "idle")
        study.select_task(task)
    # The demonstration ended (an episode stored), without reaching the goal.
    study.wait_for("episodes", episodes + 1)
    assert int(study.data("task")) == task


def demonstrate_to_goal(study: Study, task: int) -> None:
    study.keep_away_from_goal(task, 2)
    study.press("d")
    study.wait_for("mode", "demonstrate")
    study.walk_to_goal(task)
    study.wait_for("mode", "idle")


def test_each_step_needs_all_it_asks(page: Page, server: LiveServer) -> None:
    watch = Watch(server.url).attach(page)
    page.goto(f"{server.url}/study")
    page.click('[data-action="agree"]')
    page.click('[data-action="start"]')
    study = Study(page)
    tutorial = Tutorial(page)
    expect(study.teach).to_have_attribute("data-kind", "tutorial", timeout=WAIT_MS)
    study.focus()

    # Three moves asked: one is not enough, three are.
    tutorial.stays_at("move")
    study.idle_move()
    tutorial.stays_at("move")
    study.idle_move()
    study.idle_move()
    tutorial.at("demonstrate")

    # A demonstration stopped with S, or cut short by switching task, does not count.
    stop_demonstration_early(study, 0, "stop")
    tutorial.stays_at("demonstrate")
    stop_demonstration_early(study, 0, "switch task")
    tutorial.stays_at("demonstrate")
    demonstrate_to_goal(study, 0)
    tutorial.at("try")

    # T on the goal: the agent goes to a random start first and tries from there; the status
    # line says so, and no episode is recorded for the goal itself.
    goal = study.state()
    episodes = int(study.data("episodes"))
    study.press("t")
    expect(page.locator(".status")).to_contain_text(
        re.compile("The agent was on the goal of “.+” already, so it tries from a random start")
    )
    expect(page.locator("g.agent")).not_to_have_attribute("data-state", str(goal))
    assert int(study.data("episodes")) == episodes
    tutorial.at("feedback")

    # One feedback of either kind is enough (a well-moving agent need not be called bad).
    expect(page.locator('[data-action="bad"]')).to_be_enabled(timeout=WAIT_MS)
    study.press("b")
    expect(page.locator(".flash.bad.on")).to_have_count(1, timeout=5000)
    expect(tutorial.card).not_to_have_attribute("data-step", "feedback", timeout=WAIT_MS)

    if study.data("mode") != "idle":
        tutorial.at("stop")
        study.press("s")
    tutorial.at("switch")
    study.press("2")
    tutorial.at("reset")
    study.press("r")
    tutorial.at("place")
    study.idle_move()
    tutorial.stays_at("place")
    study.idle_move()
    study.idle_move()
    tutorial.at("demonstrate-second")

    # The second task's demonstration too must reach its goal.
    stop_demonstration_early(study, 1, "stop")
    tutorial.stays_at("demonstrate-second")
    stop_demonstration_early(study, 1, "switch task")
    tutorial.stays_at("demonstrate-second")
    demonstrate_to_goal(study, 1)
    tutorial.at("ready")
    expect(tutorial.next).to_be_enabled()
    # No episode of the session starts on its task's goal.
    env = domains.make(study.environment)
    rows = server.query(
        "SELECT task, start_state FROM episodes WHERE session_id = :s", s=study.session
    )
    assert len(rows) >= 7 and not [r for r in rows if env.is_goal(r.task, r.start_state)]
    watch.check()


def test_the_tutorial_step_and_the_next_agent_s_page_are_kept_by_the_server(
    page: Page, server: LiveServer
) -> None:
    """Another browser with the participant's cookie (nothing in its own storage) continues
    the tutorial at the step reached; a reload of the next agent's introduction shows it
    again, and teaching begins only from its button."""
    watch = Watch(server.url).attach(page)
    page.goto(f"{server.url}/study")
    page.click('[data-action="agree"]')
    page.click('[data-action="start"]')
    study = Study(page)
    expect(study.teach).to_have_attribute("data-kind", "tutorial", timeout=WAIT_MS)

    def in_another_browser() -> None:
        browser = page.context.browser
        assert browser is not None
        other = browser.new_context(viewport={"width": 1280, "height": 800})
        try:
            other.add_cookies(page.context.cookies())  # type: ignore[arg-type]
            elsewhere = other.new_page()
            elsewhere.goto(f"{server.url}/study")
            expect(elsewhere.locator(".tutorial-card")).to_have_attribute(
                "data-step", "demonstrate", timeout=WAIT_MS
            )
            expect(elsewhere.locator(".tutorial-count")).to_have_text("Tutorial step 2 of 10")
        finally:
            other.close()
        page.reload()
        Tutorial(page).at("demonstrate")
        study.focus()

    study.do_tutorial(begin=False, checkpoint=in_another_browser)
    meet = page.locator("h1")
    expect(meet).to_have_text(re.compile(r"Meet the .+ agent"))
    name = meet.inner_text()
    page.reload()
    expect(page.locator("h1")).to_have_text(name, timeout=WAIT_MS)
    expect(page.locator('[data-action="begin-agent"]')).to_be_visible()
    expect(page.locator(".teach-page")).to_have_count(0)
    page.click('[data-action="begin-agent"]')
    expect(study.teach).to_have_attribute("data-kind", "study", timeout=WAIT_MS)
    page.reload()
    expect(study.teach).to_have_attribute("data-kind", "study", timeout=WAIT_MS)
    watch.check()


def test_a_second_tab_is_told_in_plain_words_and_brought_up_to_date(
    page: Page, server: LiveServer
) -> None:
    watch = Watch(server.url).attach(page)
    page.goto(f"{server.url}/study")
    page.click('[data-action="agree"]')
    page.click('[data-action="start"]')
    first = Study(page)
    expect(first.teach).to_have_attribute("data-kind", "tutorial", timeout=WAIT_MS)
    other = page.context.new_page()
    other.goto(f"{server.url}/study")
    second = Study(other)
    expect(second.teach).to_have_attribute("data-kind", "tutorial", timeout=WAIT_MS)
    stale = second.seq()
    page.bring_to_front()
    first.focus()
    start = first.state()
    first.idle_move()
    # idle_move presses the first arrow that moves the agent; the second tab presses another
    # (the same request with the same sequence number would be answered as a retry).
    used = next(
        a
        for a in ("UP", "DOWN", "LEFT", "RIGHT")
        if next_state(first.environment, start, a) != start
    )
    other.bring_to_front()
    second.focus()
    second.press("ArrowDown" if used == "UP" else "ArrowUp")
    status = other.locator(".status")
    expect(status).to_contain_text(
        "The study was continued in another tab or window; this page has been brought up to date."
    )
    assert "sequence number" not in status.inner_text()
    # Brought up to date: the agent where the first tab left it, the next seq the server's.
    second.wait_state(first.state())
    expect(second.teach).not_to_have_attribute("data-seq", str(stale))
    second.idle_move()  # and teaching goes on here
    watch.check()
