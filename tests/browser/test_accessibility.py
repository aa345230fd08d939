"""Every page a person sees, checked by axe-core (bundled by axe-playwright-python: nothing is
fetched) against the WCAG 2.0 and 2.1 A and AA rules: the MTurk replica's pages, the preview,
consent, each tutorial step, the teaching page of each domain (idle, demonstrating, the agent
trying, after feedback), the attention check between agents (being taken, and recorded), the
completion page, the error pages, the errors the study's page draws
itself (a participant the server no longer knows, a request the server failed), the login page
and the dashboard (its list, a participant, a curve, a replay). Each page or state is checked in
a 1280x800, a 1280x720 and a 1024x640 window (what scrolls, and so must take the keyboard's
focus, changes with the size); each page or state in each size is its own test.

The pages are reached once per module by driving real studies (a Mechanical Turk study with its
tutorial, a lab study with the three domains); each test looks at what axe found there."""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from playwright.sync_api import Browser, Frame, Page, Route, expect

from tests.browser.conftest import (
    WAIT_MS,
    LiveServer,
    Study,
    admin_login,
    axe_violations,
    domain_toml,
    run_live_server,
    study_frame,
    study_toml,
)

# Whole studies driven in Chromium to reach every page, each checked in three window sizes
# (about three minutes): the slow tier, which CI runs.
pytestmark = [pytest.mark.browser, pytest.mark.slow]

DOMAINS = ("navigation", "farming", "gravity")
TUTORIAL_STEPS = (
    "move",
    "demonstrate",
    "try",
    "feedback",
    "switch",
    "reset",
    "place",
    "demonstrate-second",
    "ready",
)
TEACHING_STATES = ("idle", "demonstrating", "agent-trying", "after-feedback")
MTURK_STATES = (
    "login",
    "mturk-hit-page",
    "mturk-preview-frame",
    "preview",
    "mturk-work-frame",
    "consent",
    "instructions",
    *(f"tutorial-{step}" for step in TUTORIAL_STEPS),
    "meet-the-next-agent",
    "confirm-next-agent",
    "completion",
    "mturk-submitted",
    "mturk-hit-page-with-assignments",
    "dashboard-list",
    "dashboard-participant",
    "dashboard-curve",
    "dashboard-replay",
    "refused-arrival",
    "already-taken-part",
    "invalid-link",
)
LAB_STATES = (
    "declined",
    *(f"teaching-{domain}-{state}" for domain in DOMAINS for state in TEACHING_STATES),
    "lab-completion",
    "place-not-found",
    "something-went-wrong",
)
CHECK_STATES = ("attention-check", "attention-check-recorded")


SIZES = ((1280, 800), (1280, 720), (1024, 640))
SIZE_NAMES = tuple(f"{width}x{height}" for width, height in SIZES)
SETTLED = "() => new Promise((done) => requestAnimationFrame(() => requestAnimationFrame(done)))"


class Found(dict[str, list[str]]):
    """ "state@size" -> its violations; ``error`` says where driving the pages stopped."""

    error: str | None = None

    def check(self, name: str, target: Page | Frame) -> None:
        """Axe's findings in each window size (the page laid out anew for each), then back to
        the first size, in which the pages are driven."""
        page = target if isinstance(target, Page) else target.page
        for (width, height), size in zip(SIZES, SIZE_NAMES, strict=True):
            page.set_viewport_size({"width": width, "height": height})
            target.evaluate(SETTLED)
            self[f"{name}@{size}"] = axe_violations(target)
        page.set_viewport_size({"width": SIZES[0][0], "height": SIZES[0][1]})
        target.evaluate(SETTLED)


def drive(found: Found, steps: Callable[[], None]) -> Found:
    try:
        steps()
    except Exception as error:  # each state's test reports it; the others still pass
        found.error = f"{type(error).__name__}: {error}"
    return found


def new_page(browser: Browser, context_args: dict[str, Any]) -> Page:
    return browser.new_context(**context_args).new_page()


# -- the Mechanical Turk study: replica, preview, tutorial, completion, dashboard, errors ------
@pytest.fixture(scope="module")
def mturk_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    config = study_toml(
        mode="mturk",
        domains_toml=domain_toml("navigation", "two-rooms"),
        learners='["cloning"]',
        agents=1,
    )
    yield from run_live_server(tmp_path_factory.mktemp("accessibility-mturk"), config)


@pytest.fixture(scope="module")
def mturk_found(
    browser: Browser, browser_context_args: dict[str, Any], mturk_server: LiveServer
) -> Iterator[Found]:
    server = mturk_server
    page = new_page(browser, browser_context_args)
    found = Found()

    def steps() -> None:
        page.goto(f"{server.url}/dashboard/login?next=/mturk")
        found.check("login", page)
        admin_login(page, server, "/mturk")
        found.check("mturk-hit-page", page)
        page.fill("#workerId", "A11YWORKER")
        page.click('[data-action="preview"]')
        frame = study_frame(page)
        expect(frame.locator(".preview-note")).to_be_visible()
        found.check("mturk-preview-frame", page)
        found.check("preview", frame)
        page.click('[data-action="accept"]')
        page.wait_for_url(re.compile(r"/mturk/work/\d+$"))
        frame = study_frame(page)
        expect(frame.locator('[data-action="agree"]')).to_be_visible()
        found.check("mturk-work-frame", page)
        found.check("consent", frame)
        study = Study(page, frame)
        frame.locator('[data-action="agree"]').click()
        expect(frame.locator('[data-action="start"]')).to_be_visible()
        found.check("instructions", frame)
        frame.locator('[data-action="start"]').click()
        expect(study.teach).to_have_attribute("data-kind", "tutorial", timeout=WAIT_MS)
        study.do_tutorial(
            begin=False, on_step=lambda step: found.check(f"tutorial-{step}", study.frame)
        )
        found.check("meet-the-next-agent", frame)
        study.press("Enter")
        expect(study.teach).to_have_attribute("data-kind", "study", timeout=WAIT_MS)
        for task in range(frame.locator(".task").count()):
            study.demonstrate(task)
        study.press("n")
        expect(frame.locator('[data-action="confirm-next"]')).to_be_visible()
        found.check("confirm-next-agent", frame)
        study.press("Enter")
        expect(frame.locator('[data-testid="completion-code"]')).to_be_visible(timeout=WAIT_MS)
        found.check("completion", frame)
        frame.locator('[data-action="submit-hit"]').click()
        page.wait_for_url(re.compile(r"/mturk/externalSubmit"))
        expect(page.locator("#submitted")).to_be_visible()
        found.check("mturk-submitted", page)
        page.goto(f"{server.url}/mturk")
        expect(page.locator("#assignments")).to_be_visible()
        found.check("mturk-hit-page-with-assignments", page)

        page.goto(f"{server.url}/dashboard")
        row = page.locator("#participants tr[data-participant]")
        expect(row).to_have_count(1)
        found.check("dashboard-list", page)
        row.click()
        expect(page.locator("#detail .session-card").first).to_be_visible()
        found.check("dashboard-participant", page)
        expect(page.locator('#detail svg.curve:not([data-points="0"])').first).to_be_visible(
            timeout=WAIT_MS
        )
        found.check("dashboard-curve", page)
        page.locator('#detail [data-action="replay"]').last.click()
        expect(page.locator("#replay .replay-event")).to_contain_text("Event 0")
        found.check("dashboard-replay", page)

        # Error pages, in a browser that has never been here.
        stranger = new_page(browser, browser_context_args)
        try:
            stranger.goto(f"{server.url}/study")
            expect(stranger.locator("h1")).to_have_text("Please open the study from its link")
            found.check("refused-arrival", stranger)
            stranger.goto(
                f"{server.url}/study?assignmentId=A11YOTHER&hitId=H&workerId=A11YWORKER"
                f"&turkSubmitTo={server.url}"
            )
            expect(stranger.locator("h1")).to_have_text("You have already taken part")
            found.check("already-taken-part", stranger)
            stranger.goto(f"{server.url}/study?workerId={'x' * 300}&assignmentId=A&hitId=H")
            expect(stranger.locator("h1")).to_have_text("This study link is not valid")
            found.check("invalid-link", stranger)
        finally:
            stranger.context.close()

    yield drive(found, steps)
    page.context.close()


@pytest.mark.parametrize("size", SIZE_NAMES)
@pytest.mark.parametrize("state", MTURK_STATES)
def test_mturk_study_pages_have_no_wcag_violation(
    mturk_found: Found, state: str, size: str
) -> None:
    key = f"{state}@{size}"
    assert key in mturk_found, f"not reached: {mturk_found.error}"
    assert mturk_found[key] == [], "\n".join(mturk_found[key])


# -- a lab study in each domain: the teaching page's states ------------------------------------
@pytest.fixture(scope="module")
def lab_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    domains = (
        domain_toml("navigation", "two-rooms")
        + domain_toml("farming", "two-fields")
        + domain_toml("gravity", "choices")
    )
    config = study_toml(
        mode="lab", domains_toml=domains, learners='["cloning"]', agents=1, tutorial=False
    )
    yield from run_live_server(tmp_path_factory.mktemp("accessibility-lab"), config)


def teaching_states(study: Study, found: Found) -> str:
    """Idle, demonstrating, the agent trying and after feedback, on the first task; returns
    the domain."""
    page = study.page
    expect(study.teach).to_be_visible(timeout=WAIT_MS)
    domain = re.search(r"domain-(\w+)", str(study.teach.get_attribute("class")))
    assert domain is not None
    name = domain.group(1)
    found.check(f"teaching-{name}-idle", page)
    study.focus()
    study.keep_away_from_goal(0, 2)
    study.press("d")
    study.wait_for("mode", "demonstrate")
    study.walk_to_goal(0, limit=1)
    found.check(f"teaching-{name}-demonstrating", page)
    study.walk_to_goal(0)
    study.wait_for("mode", "idle")
    study.press("t")
    expect(page.locator('[data-action="good"]')).to_be_enabled(timeout=WAIT_MS)
    found.check(f"teaching-{name}-agent-trying", page)
    study.press("g")
    expect(page.locator(".flash.good.on")).to_have_count(1, timeout=5000)
    found.check(f"teaching-{name}-after-feedback", page)
    if study.data("mode") == "agent":
        study.press("s")
    study.wait_for("mode", "idle")
    return name


@pytest.fixture(scope="module")
def lab_found(
    browser: Browser, browser_context_args: dict[str, Any], lab_server: LiveServer
) -> Iterator[Found]:
    server = lab_server
    found = Found()
    pages: list[Page] = []

    def steps() -> None:
        declining = new_page(browser, browser_context_args)
        pages.append(declining)
        declining.goto(f"{server.url}/study")
        declining.click('[data-action="decline"]')
        expect(declining.locator("h1")).to_have_text("Thank you")
        found.check("declined", declining)
        taught = []
        for _ in DOMAINS:  # the domains are balanced: three participants, three domains
            page = new_page(browser, browser_context_args)
            pages.append(page)
            page.goto(f"{server.url}/study")
            page.click('[data-action="agree"]')
            page.click('[data-action="start"]')
            study = Study(page)
            taught.append(teaching_states(study, found))
        assert sorted(taught) == sorted(DOMAINS)
        # The last participant finishes: the lab study's completion page.
        for task in range(study.frame.locator(".task").count()):
            if (
                int(
                    str(
                        study.frame.locator(f'.task[data-task="{task}"]').get_attribute(
                            "data-count"
                        )
                    )
                )
                == 0
            ):
                study.demonstrate(task)
        study.press("n")
        expect(page.locator('[data-action="confirm-next"]')).to_be_visible()
        study.press("Enter")
        expect(page.locator('[data-testid="completion-code"]')).to_be_visible(timeout=WAIT_MS)
        found.check("lab-completion", page)
        in_page_errors(browser, browser_context_args, server, found, pages)

    yield drive(found, steps)
    for page in pages:
        page.context.close()


def in_page_errors(
    browser: Browser,
    browser_context_args: dict[str, Any],
    server: LiveServer,
    found: Found,
    pages: list[Page],
) -> None:
    """The errors the study's page draws in place of a step: the participant's token is no
    longer known to the server (401), and the server fails a request (500)."""
    forgotten = new_page(browser, browser_context_args)
    pages.append(forgotten)
    forgotten.goto(f"{server.url}/study")
    expect(forgotten.locator('[data-action="agree"]')).to_be_visible()
    # The newest participant's token is no longer valid.
    server.query(
        "UPDATE participants SET token_hash = :other WHERE id = (SELECT max(id) FROM participants)",
        other="0" * 64,
    )
    forgotten.click('[data-action="agree"]')
    expect(forgotten.locator("h1")).to_have_text("Your place in the study could not be found")
    found.check("place-not-found", forgotten)

    failing = new_page(browser, browser_context_args)
    pages.append(failing)

    def server_error(route: Route) -> None:  # as the server answers an unhandled error
        route.fulfill(status=500, content_type="text/plain", body="Internal Server Error")

    failing.route("**/api/participant/consent", server_error)
    failing.goto(f"{server.url}/study")
    failing.click('[data-action="agree"]')
    expect(failing.locator("h1")).to_have_text("Something went wrong")
    expect(failing.locator("main")).to_contain_text("Internal Server Error")
    found.check("something-went-wrong", failing)


@pytest.mark.parametrize("size", SIZE_NAMES)
@pytest.mark.parametrize("state", LAB_STATES)
def test_lab_study_pages_have_no_wcag_violation(lab_found: Found, state: str, size: str) -> None:
    key = f"{state}@{size}"
    assert key in lab_found, f"not reached: {lab_found.error}"
    assert lab_found[key] == [], "\n".join(lab_found[key])


def test_the_rule_set_is_wcag_a_and_aa(tmp_path: Path, page: Page) -> None:
    """The check can fail: a page with an unlabelled field, an image without a text and grey
    text on white breaks three WCAG rules, which axe reports."""
    sample = tmp_path / "bad.html"
    sample.write_text(
        '<!doctype html><html lang="en"><head><title>t</title></head><body><main>'
        '<input type="text"><img src="x.png">'
        '<p style="color:#bbb;background:#fff">faint</p></main></body></html>'
    )
    page.goto(sample.as_uri())
    rules = {line.split(" ")[0] for line in axe_violations(page)}
    assert {"label", "image-alt", "color-contrast"} <= rules


# -- words for what is drawn, announcements, reduced motion, 200% zoom -------------------------
def start_teaching(page: Page, server: LiveServer) -> Study:
    page.goto(f"{server.url}/study")
    page.click('[data-action="agree"]')
    page.click('[data-action="start"]')
    study = Study(page)
    expect(study.teach).to_be_visible(timeout=WAIT_MS)
    return study


def test_the_grid_and_every_state_change_are_said_in_words(
    page: Page, lab_server: LiveServer
) -> None:
    study = start_teaching(page, lab_server)
    grid = page.locator(".board svg.grid")
    described = page.locator(f"#{grid.get_attribute('aria-describedby')}")
    agent = page.locator("g.agent")
    row = int(str(agent.get_attribute("data-row"))) + 1
    column = int(str(agent.get_attribute("data-column"))) + 1
    expect(described).to_contain_text(f"The agent is at row {row}, column {column}")
    expect(described).to_contain_text("The goal of the selected task, “")
    domain = study.data("environment")
    if domain == "two-fields":
        expect(described).to_contain_text("It carries no machine.")
        expect(described).to_contain_text("The plow is at row")
    elif domain == "choices":
        feature = str(agent.get_attribute("data-feature"))
        expect(described).to_contain_text(f"Its gravity {feature}: cannot move")
        expect(described).to_contain_text("A green cell (G) at row")
    # It follows the agent.
    study.focus()
    study.idle_move()
    row = int(str(agent.get_attribute("data-row"))) + 1
    column = int(str(agent.get_attribute("data-column"))) + 1
    expect(described).to_contain_text(f"The agent is at row {row}, column {column}")
    # A demonstration to the goal: the end of the episode and the learning are announced.
    log = page.get_by_role("log")
    expect(log).to_have_attribute("aria-live", "polite")
    study.demonstrate(0)
    expect(log).to_contain_text("Episode ended. Well done: the demonstration reached the goal")
    expect(log).to_contain_text("The agent is learning from your last episode.")
    expect(log).to_contain_text("The agent has learned from your last episode.", timeout=WAIT_MS)
    # The agent's try, and feedback on it.
    study.press("t")
    expect(page.locator('[data-action="good"]')).to_be_enabled(timeout=WAIT_MS)
    expect(log).to_contain_text("The agent is trying")
    study.press("g")
    expect(log).to_contain_text("Feedback recorded: good.")
    study.press("b")
    expect(log).to_contain_text("Feedback recorded: bad.")
    # A refusal is said too.
    study.press("n")
    expect(log).to_contain_text("Not yet.")


def agent_motion(browser: Browser, server: LiveServer, reduced: bool) -> dict[str, str]:
    context = browser.new_context(
        viewport={"width": 1280, "height": 800}, reduced_motion="reduce" if reduced else None
    )
    try:
        page = context.new_page()
        start_teaching(page, server)
        return dict(
            page.evaluate(
                """() => {
                  const style = (selector) => getComputedStyle(document.querySelector(selector));
                  return {
                    step: style("g.agent").transitionDuration,
                    goal: style(".goal-selected .goal-outline").animationName,
                  };
                }"""
            )
        )
    finally:
        context.close()


def test_the_agent_s_steps_are_not_animated_when_the_participant_asks_for_less_motion(
    browser: Browser, lab_server: LiveServer
) -> None:
    assert agent_motion(browser, lab_server, reduced=False) == {"step": "0.22s", "goal": "march"}
    assert agent_motion(browser, lab_server, reduced=True) == {"step": "0s", "goal": "none"}


def test_the_teaching_page_is_usable_at_200_percent_zoom(
    browser: Browser, lab_server: LiveServer
) -> None:
    """A 1280x800 window zoomed to 200%: 640x400 CSS pixels at two device pixels each. Nothing
    needs horizontal scrolling, the grid stays large enough to see, the keys move the agent,
    and Next agent can be reached."""
    context = browser.new_context(viewport={"width": 640, "height": 400}, device_scale_factor=2)
    try:
        page = context.new_page()
        study = start_teaching(page, lab_server)
        page.wait_for_timeout(300)  # the grid is fitted to its frame after layout
        assert page.evaluate("document.documentElement.scrollWidth <= innerWidth")
        grid = page.locator(".board svg.grid").bounding_box()
        assert grid is not None
        assert grid["x"] >= 0 and grid["x"] + grid["width"] <= 640
        # At least half the window's width or height (not a thumbnail above a clipped panel).
        assert grid["width"] >= 320 or grid["height"] >= 200, grid
        study.focus()
        study.idle_move()
        next_button = page.locator('[data-action="next"]')
        next_button.scroll_into_view_if_needed()
        expect(next_button).to_be_in_viewport()
        box = next_button.bounding_box()
        assert box is not None and box["x"] >= 0 and box["x"] + box["width"] <= 640
        expect(page.locator(".next-reason")).to_be_in_viewport()
    finally:
        context.close()


# -- the attention check between two agents ---------------------------------------------------
@pytest.fixture(scope="module")
def check_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    config = study_toml(
        mode="lab",
        domains_toml=domain_toml("navigation", "wall"),
        learners='["cloning"]',
        agents=2,
        allow_anonymous=True,
        tutorial=False,
    )
    checks = "\n[attention_checks]\nenabled = true\nmoves = 8\n"
    yield from run_live_server(tmp_path_factory.mktemp("accessibility-check"), config + checks)


@pytest.fixture(scope="module")
def check_found(
    browser: Browser, browser_context_args: dict[str, Any], check_server: LiveServer
) -> Iterator[Found]:
    page = new_page(browser, browser_context_args)
    found = Found()

    def steps() -> None:
        page.goto(f"{check_server.url}/study")
        page.click('[data-action="agree"]')
        page.click('[data-action="start"]')
        study = Study(page)
        expect(study.teach).to_be_visible(timeout=WAIT_MS)
        study.focus()
        for task in range(page.locator(".task").count()):
            study.demonstrate(task)
        study.press("n")
        expect(page.locator('[data-action="confirm-next"]')).to_be_visible()
        study.press("Enter")
        status = page.locator(".check-status")
        expect(status).to_have_text("8 moves left.", timeout=WAIT_MS)
        study.press("ArrowUp")
        expect(status).to_have_text("7 moves left.", timeout=WAIT_MS)
        found.check("attention-check", page)
        for left, key in enumerate(["ArrowUp"] * 3 + ["ArrowRight"] * 3):
            study.press(key)
            expect(status).to_have_text(f"{6 - left} {'move' if left == 5 else 'moves'} left.")
        study.press("ArrowRight")
        expect(page.locator('[data-action="after-check"]')).to_be_focused(timeout=WAIT_MS)
        found.check("attention-check-recorded", page)

    yield drive(found, steps)
    page.context.close()


@pytest.mark.parametrize("size", SIZE_NAMES)
@pytest.mark.parametrize("state", CHECK_STATES)
def test_the_attention_check_has_no_wcag_violation(
    check_found: Found, state: str, size: str
) -> None:
    key = f"{state}@{size}"
    assert key in check_found, f"not reached: {check_found.error}"
    assert check_found[key] == [], "\n".join(check_found[key])
