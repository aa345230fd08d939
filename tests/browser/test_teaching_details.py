"""Details of the teaching page a participant notices: the rule for going on to the next agent
is one (every task needs a demonstrated move, a demonstration stopped early counts too) and
the tutorial asks for it and says it; the last agent's confirmation offers no next agent; a
move that leaves the agent where it was is shown and said; "=" (the "+" key unshifted) is Good;
inside the platform's frame, the hint to click the page stays off the grid."""

from __future__ import annotations

import re
from collections.abc import Iterator

import pytest
from playwright.sync_api import Page, expect

from tests.browser.conftest import (
    WAIT_MS,
    LiveServer,
    Study,
    Watch,
    admin_login,
    domain_toml,
    next_state,
    run_live_server,
    study_frame,
    study_toml,
)

pytestmark = pytest.mark.browser
RULE = "Every task has at least one demonstrated move"


@pytest.fixture(scope="module")
def lab_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    config = study_toml(
        mode="lab",
        domains_toml=domain_toml("navigation", "wall"),
        learners='["cloning"]',
        agents=2,
        tutorial=False,
    )
    yield from run_live_server(tmp_path_factory.mktemp("teaching-details"), config)


@pytest.fixture(scope="module")
def farming_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    """A farming study, whose tutorial has three tasks; through the MTurk replica."""
    config = study_toml(
        mode="mturk",
        domains_toml=domain_toml("farming", "two-fields"),
        learners='["cloning"]',
        agents=1,
    )
    yield from run_live_server(tmp_path_factory.mktemp("teaching-details-farming"), config)


def start(page: Page, server: LiveServer) -> Study:
    page.goto(f"{server.url}/study")
    page.click('[data-action="agree"]')
    page.click('[data-action="start"]')
    study = Study(page)
    expect(study.teach).to_have_attribute("data-kind", "study", timeout=WAIT_MS)
    study.focus()
    return study


def blocked_direction(study: Study) -> str:
    """An arrow that leaves the agent on its cell from where it is (moving it there first)."""
    for _ in range(12):
        state = study.state()
        for action in ("UP", "DOWN", "LEFT", "RIGHT"):
            if next_state(study.environment, state, action) == state:
                return action
        study.move("UP")
    raise AssertionError("no blocked move found")


def test_a_move_that_leaves_the_agent_in_place_is_shown_and_said(
    page: Page, lab_server: LiveServer
) -> None:
    watch = Watch(lab_server.url).attach(page)
    study = start(page, lab_server)
    agent = page.locator("g.agent")
    status = page.locator(".status")
    # With no mode on.
    direction = blocked_direction(study)
    study.move(direction)
    expect(agent).to_have_attribute("data-bumps", "1")
    expect(agent).to_have_attribute("data-bump", direction.lower())
    # The red bar marks that side of the agent's cell (it shows for a moment only).
    edge = {"UP": ("y", "0"), "DOWN": ("y", "91"), "LEFT": ("x", "0"), "RIGHT": ("x", "91")}
    name, value = edge[direction]
    expect(page.locator("g.agent .bump-mark")).to_have_attribute(name, value)
    expect(status).to_contain_text(
        f"Blocked: the agent could not move {direction.lower()} and stayed where it was."
    )
    expect(page.get_by_role("log")).to_contain_text(f"could not move {direction.lower()}")
    # The next move that goes somewhere clears it.
    study.idle_move()
    expect(status).not_to_contain_text("Blocked")
    # In a demonstration: the move counts, and the page says so.
    study.press("d")
    study.wait_for("mode", "demonstrate")
    direction = blocked_direction(study)
    actions = int(study.data("actions"))
    study.move(direction)
    expect(agent).to_have_attribute("data-bumps", "2")
    assert int(study.data("actions")) == actions + 1
    expect(status).to_contain_text("the move still counts as demonstrated")
    watch.check()


def test_equals_is_good_feedback(page: Page, lab_server: LiveServer) -> None:
    study = start(page, lab_server)
    study.demonstrate(0)
    study.press("t")
    expect(page.locator('[data-action="good"]')).to_be_enabled(timeout=WAIT_MS)
    study.press("=")
    expect(page.locator(".flash.good.on")).to_have_count(1, timeout=5000)
    expect(page.get_by_role("log")).to_contain_text("Feedback recorded: good.")
    rows = lab_server.query(
        "SELECT feedback FROM events WHERE session_id = :s AND kind = 'feedback'",
        s=study.session,
    )
    assert [row.feedback for row in rows] == [1]


def stop_after_one_move(study: Study, task: int) -> None:
    """A demonstration of ``task`` stopped (S) after one move, before its goal."""
    study.select_task(task)
    study.keep_away_from_goal(task, 3)
    study.press("d")
    study.wait_for("mode", "demonstrate")
    study.walk_to_goal(task, limit=1)
    study.press("s")
    study.wait_for("mode", "idle")


def test_one_rule_for_going_on_and_no_next_agent_after_the_last(
    page: Page, lab_server: LiveServer
) -> None:
    watch = Watch(lab_server.url).attach(page)
    study = start(page, lab_server)
    next_button = page.locator('[data-action="next"]')
    reason = page.locator(".next-reason")
    expect(reason).to_contain_text("Every task needs at least one demonstrated move first")
    tasks = page.locator(".task").count()
    # Demonstrations stopped before the goal count: the page and the server agree.
    for task in range(tasks):
        expect(next_button).to_be_disabled()
        stop_after_one_move(study, task)
        expect(page.locator(f'.task[data-task="{task}"] .task-count')).to_have_text(
            "✓ 1 move shown"
        )
    expect(next_button).to_be_enabled()
    expect(reason).to_contain_text(RULE)
    study.press("n")
    dialog = page.locator("dialog.confirm")
    expect(page.locator('[data-action="confirm-next"]')).to_have_text(
        re.compile("Yes, next agent$")
    )
    expect(dialog).to_contain_text("You cannot come back to this agent")
    study.press("Enter")
    page.locator('[data-action="begin-agent"]').click(timeout=WAIT_MS)
    expect(study.teach).to_contain_text("Agent 2 of 2")
    study.focus()
    for task in range(tasks):
        stop_after_one_move(study, task)
    study.press("n")
    confirm = page.locator('[data-action="confirm-next"]')
    expect(confirm).to_have_text(re.compile("Yes, finish teaching$"))
    expect(dialog).not_to_contain_text("next agent")
    expect(dialog).to_contain_text("This is the last agent: the study ends here")
    study.press("Enter")
    expect(page.locator('[data-testid="completion-code"]')).to_be_visible(timeout=WAIT_MS)
    watch.check()


def test_the_tutorial_asks_for_every_task_and_the_hint_stays_off_the_grid(
    page: Page, farming_server: LiveServer
) -> None:
    server = farming_server
    watch = Watch(server.url).attach(page)
    admin_login(page, server, "/mturk")
    page.fill("#workerId", "WDETAILS")
    page.click('[data-action="accept"]')
    page.wait_for_url(re.compile(r"/mturk/work/\d+$"))
    frame = study_frame(page)
    frame.locator('[data-action="agree"]').click()
    frame.locator('[data-action="start"]').click()
    study = Study(page, frame)
    expect(study.teach).to_have_attribute("data-kind", "tutorial", timeout=WAIT_MS)

    # The keys reach the study only when its frame has the focus: the hint asks for a click,
    # beside the grid (not over its first row and the goals' names).
    page.locator(".hitbar-title").click()
    hint = frame.locator(".focus-hint")
    expect(hint).to_be_visible(timeout=5000)
    hint_box = hint.bounding_box()
    grid_box = frame.locator(".board svg.grid").bounding_box()
    assert hint_box is not None and grid_box is not None
    assert hint_box["y"] + hint_box["height"] <= grid_box["y"] + 1, (hint_box, grid_box)
    hint.click()
    expect(hint).to_be_hidden(timeout=5000)

    card = frame.locator(".tutorial-card")
    demonstrate_step = card.filter(has_text="Show it a task")
    seen: list[str] = []

    def on_step(name: str) -> None:
        seen.append(name)
        if name == "demonstrate":
            expect(demonstrate_step).not_to_contain_text("does not count")
        if name == "demonstrate-second" and seen.count(name) == 2:
            # The first two tasks shown, the third not yet: the step stays and names it, and
            # says the study's rule.
            expect(card).to_contain_text("Now demonstrate “Crops”")
            expect(card).to_contain_text(
                "Next agent opens once every task has at least one demonstrated move"
            )
            expect(frame.locator('[data-action="next"]')).to_be_disabled()

    study.do_tutorial(on_step=on_step)
    assert seen.count("demonstrate-second") == 2
    watch.check()
