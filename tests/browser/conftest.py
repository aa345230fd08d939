"""Fixtures of the browser tests: Debian's Chromium (never a downloaded browser), a live study
server (uvicorn in a thread) on a fresh SQLite database migrated by the project's own code, with
small study configurations, and helpers that drive the participant's page with real key presses.

Screenshots go to ``$BAM_SCREENSHOT_DIR`` (``scripts/screenshots.py`` points it at
``docs/screenshots``), or to a temporary folder.
"""

from __future__ import annotations

import os
import re
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Executor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from axe_playwright_python.sync_playwright import Axe
from playwright.sync_api import ConsoleMessage, Frame, Page, Request, expect
from sqlalchemy import create_engine, text

from server import domains
from server.app.main import create_app
from server.app.settings import Settings
from server.domains.base import ACTIONS
from tests.support.databases import migrated_sqlite
from tests.support.server import live

ADMIN_TOKEN = "browser-test-admin-token"
CHROMIUM = "/usr/bin/chromium"
KEY_OF = {"UP": "ArrowUp", "DOWN": "ArrowDown", "LEFT": "ArrowLeft", "RIGHT": "ArrowRight"}
WAIT_MS = 60_000  # learner updates are real: the first ones include starting the worker process

# Real learners with fewer optimisation steps, so that an update takes a fraction of a second.
FAST_LEARNERS = """
[learner_settings.bam]
alternations = 1
cost_steps = 4
dynamics_steps = 4

[learner_settings.model-based]
dynamics_steps = 6
cost_steps = 6

[learner_settings.cloning]
steps = 20
"""
COLOURS = """
[[colours]]
name = "orange"
hex = "#E69F00"

[[colours]]
name = "sky blue"
hex = "#56B4E9"

[[colours]]
name = "green"
hex = "#009E73"

[[colours]]
name = "vermillion"
hex = "#D55E00"
"""


def domain_toml(name: str, *environments: str) -> str:
    """A study file's ``[[domains]]`` table teaching ``environments`` of domain ``name``."""
    listed = ", ".join(f'"{e}"' for e in environments)
    return f'\n[[domains]]\nname = "{name}"\nenvironments = [{listed}]\n'


def study_toml(
    *,
    mode: str,
    domains_toml: str,
    learners: str = '["bam", "cloning"]',
    agents: int = 2,
    allow_anonymous: bool = False,
    reveal_gravity: bool = False,
    tutorial: bool = True,
) -> str:
    """A small study: the paper's shape (tutorial, agents in random order) with fewer agents."""
    return f"""
title = "Teach a robot"
learners = {learners}
agents_per_environment = {agents}
allow_repeat_workers = false
allow_anonymous = {str(allow_anonymous).lower()}
reveal_gravity = {str(reveal_gravity).lower()}
payment = "You will be paid 3.00 USD for completing this study, which takes about 30 minutes."
consent = \"\"\"
This study is part of a research project on how people teach learning agents (simple simulated
robots) to do tasks.

We record what you do in the interface. Taking part is voluntary; you may stop at any time.

By choosing "I agree" you confirm that you are at least 18 years old and agree to take part.
\"\"\"

[completion]
mode = "{mode}"

[tutorial]
enabled = {str(tutorial).lower()}
learner = "cloning"
colour = {{ name = "black", hex = "#000000" }}
{domains_toml}
{FAST_LEARNERS}
{COLOURS}
"""


# -- the browser ----------------------------------------------------------------------------
@pytest.fixture(scope="session")
def browser_type_launch_args() -> dict[str, Any]:
    return {
        "executable_path": CHROMIUM,
        "args": [
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
        ],
    }


@pytest.fixture(scope="session")
def browser_context_args() -> dict[str, Any]:
    return {"viewport": {"width": 1280, "height": 800}}


@pytest.fixture(scope="session")
def screenshot_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    configured = os.environ.get("BAM_SCREENSHOT_DIR")
    path = Path(configured) if configured else tmp_path_factory.mktemp("screenshots")
    path.mkdir(parents=True, exist_ok=True)
    return path


# -- the live server ------------------------------------------------------------------------
@dataclass
class LiveServer:
    url: str
    database_url: str

    def query(self, sql: str, **params: Any) -> list[Any]:
        """Rows straight from the study's database (what the server committed); a statement
        that changes rows is committed (as another process's change would be)."""
        engine = create_engine(self.database_url)
        try:
            with engine.begin() as connection:
                result = connection.execute(text(sql), params)
                return list(result) if result.returns_rows else []
        finally:
            engine.dispose()


def run_live_server(
    tmp: Path,
    config: str,
    executor: Executor | None = None,
    measure_capacity: bool = False,
    server_share: Callable[[threading.Event], float] | None = None,
) -> Iterator[LiveServer]:
    """A study server on a free port: settings from the BAM_* environment variables, a fresh
    SQLite database at the migrations' head (``tests.support.databases``), learner updates in a process (or in
    ``executor``); with ``measure_capacity`` it times the study's reference updates, as
    ``serve`` does, and the server's own work per update with ``server_share``."""
    config_path = tmp / "study.toml"
    config_path.write_text(config, encoding="utf-8")
    database_url = migrated_sqlite(tmp / "study.db")
    known = set(domains.names())
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("BAM_DATABASE_URL", database_url)
        mp.setenv("BAM_ADMIN_TOKEN", ADMIN_TOKEN)
        mp.setenv("BAM_STUDY_CONFIG", str(config_path))
        mp.setenv("BAM_UPDATE_WORKERS", "1")
        mp.setenv("BAM_UPDATE_WORKER_NICENESS", "0")
        mp.setenv("BAM_AGENT_WAIT_SECONDS", "120")
        app = create_app(
            Settings(),
            executor=executor,
            measure_capacity=measure_capacity,
            server_share=server_share,
        )
    try:
        with live(app) as url:
            yield LiveServer(url, database_url)
    finally:
        # The study's own environments, registered in this process by the app, go with it.
        for name in set(domains.names()) - known:
            domains.unregister(name)


# -- watching the page ----------------------------------------------------------------------
@dataclass
class Watch:
    """Console errors, page errors and requests to any host but the server."""

    origin: str
    errors: list[str] = field(default_factory=list)
    foreign: list[str] = field(default_factory=list)
    requests: int = 0

    def attach(self, page: Page) -> Watch:
        page.on("console", self.console)
        page.on("pageerror", lambda error: self.errors.append(f"page error: {error}"))
        page.on("request", self.request)
        return self

    def console(self, message: ConsoleMessage) -> None:
        if message.type == "error":
            self.errors.append(f"console: {message.text} ({message.location})")

    def request(self, request: Request) -> None:
        self.requests += 1
        url = request.url
        if not (url.startswith(self.origin + "/") or url.startswith(("data:", "about:"))):
            self.foreign.append(url)

    def check(self) -> None:
        assert self.requests > 0
        assert self.errors == [], self.errors
        assert self.foreign == [], self.foreign


# -- driving the study page -----------------------------------------------------------------
def moves_to(environment: str, state: int, reached: Callable[[int], bool], what: str) -> list[str]:
    """The fewest moves from ``state`` to a state ``reached`` accepts, under the true dynamics
    (``what`` names it in the error when there is none)."""
    env = domains.make(environment)
    rng = np.random.default_rng(0)
    previous: dict[int, tuple[int, str] | None] = {state: None}
    queue = deque([state])
    while queue:
        current = queue.popleft()
        if reached(current):
            path: list[str] = []
            while previous[current] is not None:
                current, action = previous[current]  # type: ignore[misc]
                path.append(action)
            return path[::-1]
        for action in range(1, len(ACTIONS)):
            following = env.step(current, action, rng)
            if following not in previous:
                previous[following] = (current, ACTIONS[action])
                queue.append(following)
    raise AssertionError(f"no path to {what} from state {state} in {environment}")


def shortest_path(environment: str, state: int, task: int) -> list[str]:
    """The fewest moves from ``state`` to the task's goal under the true dynamics."""
    goal = domains.make(environment).tasks[task].reward > 0
    return moves_to(environment, state, lambda s: bool(goal[s]), f"task {task}")


def next_state(environment: str, state: int, action: str) -> int:
    env = domains.make(environment)
    return env.step(state, ACTIONS.index(action), np.random.default_rng(0))


class Study:
    """The participant's page in ``frame`` (the platform's iframe, or the page itself)."""

    def __init__(self, page: Page, frame: Frame | None = None) -> None:
        self.page = page
        self.frame = frame or page.main_frame

    def refind(self) -> None:
        """After a reload the iframe is a new frame."""
        if self.frame is not self.page.main_frame:
            self.frame = study_frame(self.page)

    # reading
    @property
    def teach(self) -> Any:
        return self.frame.locator(".teach-page")

    def data(self, name: str) -> str:
        return str(self.teach.get_attribute(f"data-{name}"))

    def state(self) -> int:
        return int(str(self.frame.locator("g.agent").get_attribute("data-state")))

    @property
    def session(self) -> int:
        return int(self.data("session"))

    @property
    def environment(self) -> str:
        return self.data("environment")

    def seq(self) -> int:
        return int(self.data("seq"))

    # acting
    def focus(self) -> None:
        """Keys reach the page in the iframe once it has the focus (as for a real worker)."""
        self.frame.locator(".topbar").click()

    def press(self, key: str) -> None:
        self.page.keyboard.press(key)

    def wait_for(self, name: str, value: Any) -> None:
        expect(self.teach).to_have_attribute(f"data-{name}", str(value), timeout=WAIT_MS)

    def wait_state(self, state: int) -> None:
        expect(self.frame.locator("g.agent")).to_have_attribute(
            "data-state", str(state), timeout=WAIT_MS
        )

    def answered(self, before: int) -> None:
        """Wait until the server has answered a request sent after ``before``."""
        expect(self.teach).not_to_have_attribute("data-seq", str(before), timeout=WAIT_MS)

    def key_and_wait(self, key: str) -> None:
        before = self.seq()
        self.press(key)
        self.answered(before)

    def move(self, action: str) -> None:
        expected = next_state(self.environment, self.state(), action)
        before = self.seq()
        self.press(KEY_OF[action])
        self.answered(before)
        self.wait_state(expected)

    def select_task(self, task: int) -> None:
        if int(self.data("task")) != task:
            self.press(str(task + 1))
            self.wait_for("task", task)

    def walk_to_goal(self, task: int, limit: int | None = None) -> int:
        """Move along a shortest path; stops after ``limit`` moves. Returns the moves made."""
        path = shortest_path(self.environment, self.state(), task)
        assert path, "the agent is already at the goal"
        made = 0
        for action in path[:limit]:
            self.move(action)
            made += 1
        return made

    def keep_away_from_goal(self, task: int, moves: int) -> None:
        """Idle moves (no demonstration) until the goal is more than ``moves`` moves away."""
        for _ in range(20):
            path = shortest_path(self.environment, self.state(), task)
            if len(path) > moves:
                return
            state = self.state()
            possible = [
                a
                for a in ("UP", "DOWN", "LEFT", "RIGHT")
                if next_state(self.environment, state, a) != state
            ]
            farther = max(
                possible,
                key=lambda a: len(
                    shortest_path(self.environment, next_state(self.environment, state, a), task)
                ),
            )
            self.move(farther)
        raise AssertionError("could not move away from the goal")

    def demonstrate(self, task: int, reload_after: int | None = None) -> None:
        """Select the task, reset, demonstrate it to the goal with arrow keys (the demonstration
        ends there); ``reload_after`` reloads the page after that many moves and goes on."""
        self.select_task(task)
        before = self.seq()
        self.press("r")
        self.answered(before)
        self.keep_away_from_goal(task, (reload_after or 0) + 1)
        self.press("d")
        self.wait_for("mode", "demonstrate")
        shown = int(
            self.frame.locator(f'.task[data-task="{task}"]').get_attribute("data-count") or 0
        )
        if reload_after:
            self.walk_to_goal(task, limit=reload_after)
            state, session = self.state(), self.session
            self.page.reload()
            self.refind()
            self.wait_for("session", session)
            self.wait_for("mode", "demonstrate")
            self.wait_for("episode-actions", reload_after)
            assert self.state() == state
            self.focus()
        self.walk_to_goal(task)
        self.wait_for("mode", "idle")
        expect(self.frame.locator(f'.task[data-task="{task}"]')).not_to_have_attribute(
            "data-count", str(shown)
        )

    def idle_move(self) -> None:
        """One arrow press in idle mode that moves the agent (not a demonstration)."""
        assert self.data("mode") == "idle"
        state = self.state()
        for action in ("UP", "DOWN", "LEFT", "RIGHT"):
            if next_state(self.environment, state, action) != state:
                actions = int(self.data("actions"))
                self.move(action)
                assert int(self.data("actions")) == actions  # not a demonstrated action
                return
        raise AssertionError("the agent cannot move")

    def let_agent_try_with_feedback(self) -> None:
        """Let the agent act, press both feedback keys (a green and a red flash), stop it."""
        actions = int(self.data("actions"))
        self.press("t")
        good = self.frame.locator('[data-action="good"]')
        expect(good).to_be_enabled(timeout=WAIT_MS)
        assert int(self.data("actions")) > actions
        self.press("g")
        expect(self.frame.locator(".flash.good.on")).to_have_count(1, timeout=5000)
        self.press("b")
        expect(self.frame.locator(".flash.bad.on")).to_have_count(1, timeout=5000)
        if self.data("mode") == "agent":
            self.press("s")
        self.wait_for("mode", "idle")

    def next_agent(self) -> None:
        """Finish this agent (confirming) and begin the next one."""
        session = self.session
        self.press("n")
        confirm = self.frame.locator('[data-action="confirm-next"]')
        expect(confirm).to_be_visible()
        self.press("Enter")
        begin = self.frame.locator('[data-action="begin-agent"]')
        expect(begin).to_be_visible(timeout=WAIT_MS)
        self.press("Enter")
        expect(self.teach).to_be_visible()
        assert self.session != session

    def do_tutorial(
        self,
        screenshot: Path | None = None,
        *,
        begin: bool = True,
        checkpoint: Callable[[], None] | None = None,
        on_step: Callable[[str], None] | None = None,
    ) -> None:
        """Every step of the tutorial, as it asks; ``checkpoint`` is called at its second step,
        ``on_step`` with each step's name when the page shows it, and without ``begin`` it
        stops at the next agent's introduction page."""
        card = self.frame.locator(".tutorial-card")
        expect(self.frame.locator('[data-action="next"]')).to_be_disabled()

        def step(name: str) -> None:
            expect(card).to_have_attribute("data-step", name, timeout=WAIT_MS)
            if on_step is not None:
                on_step(name)

        self.focus()
        step("move")
        for _ in range(3):
            self.idle_move()
        step("demonstrate")
        if checkpoint is not None:
            checkpoint()
        self.keep_away_from_goal(0, 3)
        self.press("d")
        self.wait_for("mode", "demonstrate")
        if screenshot is not None:
            self.walk_to_goal(0, limit=2)
            self.frame_screenshot(screenshot)
        self.walk_to_goal(0)
        step("try")
        self.press("t")
        step("feedback")
        expect(self.frame.locator('[data-action="good"]')).to_be_enabled(timeout=WAIT_MS)
        self.press("g")
        self.press("b")
        step_or_later = re.compile("stop|switch")
        expect(card).to_have_attribute("data-step", step_or_later, timeout=WAIT_MS)
        if self.data("mode") != "idle":
            self.press("s")
        step("switch")
        self.press("2")
        step("reset")
        self.press("r")
        step("place")
        for _ in range(3):
            self.idle_move()
        step("demonstrate-second")
        self.keep_away_from_goal(1, 1)
        self.press("d")
        self.wait_for("mode", "demonstrate")
        self.walk_to_goal(1)
        # A tutorial of more than two tasks asks for a demonstration of each.
        for task in range(2, self.frame.locator(".task").count()):
            step("demonstrate-second")
            self.demonstrate(task)
        step("ready")
        next_button = self.frame.locator('[data-action="next"]')
        expect(next_button).to_be_enabled()
        self.press("n")
        expect(self.frame.locator('[data-action="begin-agent"]')).to_be_visible(timeout=WAIT_MS)
        if not begin:
            return
        self.press("Enter")
        expect(self.teach).to_have_attribute("data-kind", "study")

    def frame_screenshot(self, path: Path) -> None:
        if self.frame is self.page.main_frame:
            self.page.screenshot(path=str(path))
        else:
            self.page.locator("iframe.hitframe").screenshot(path=str(path))


def study_frame(page: Page) -> Frame:
    """The study's iframe in a replica page, once it has loaded."""
    page.wait_for_selector("iframe.hitframe")
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        for frame in page.frames:
            if frame is not page.main_frame and "/study" in frame.url and not frame.is_detached():
                return frame
        page.wait_for_timeout(50)  # lets Playwright see the frame's navigation
    raise AssertionError("the study's iframe did not load")


def admin_login(page: Page, server: LiveServer, next_path: str = "/mturk") -> None:
    page.goto(f"{server.url}/dashboard/login?next={next_path}")
    page.fill("#token", ADMIN_TOKEN)
    page.click("button[type=submit]")
    page.wait_for_url(f"{server.url}{next_path}")


# -- accessibility: axe-core (bundled by axe-playwright-python; nothing is fetched) --------------
WCAG_TAGS = ["wcag2a", "wcag2aa", "wcag21a", "wcag21aa"]
AXE = Axe()

# Transitions and other finite animations still running (a button's colour fading into its
# pressed colour for 0.12 s): axe judges the colours of the moment, so it waits for them to end.
# Endless animations (a marching outline, a pulsing prompt) move no colour axe checks.
FINITE_ANIMATIONS_RUNNING = """() => document.getAnimations().filter(
    (a) => a.playState === "running" && a.effect.getTiming().iterations !== Infinity
).length === 0"""


def axe_violations(target: Page | Frame) -> list[str]:
    """Every WCAG 2.0/2.1 A and AA violation axe finds in ``target`` (a page without its
    iframes, or one frame) once its transitions have ended, one line each: rule, element,
    what is wrong."""
    target.wait_for_function(FINITE_ANIMATIONS_RUNNING, timeout=5000)
    results = AXE.run(
        target,
        options={
            "runOnly": {"type": "tag", "values": WCAG_TAGS},
            "resultTypes": ["violations"],
            "iframes": False,
        },
    )
    return [
        f"{violation['id']} at {node['target']}: {violation['help']} "
        f"({(node.get('failureSummary') or '').replace(chr(10), ' ')})"
        for violation in results.response["violations"]
        for node in violation["nodes"]
    ]
