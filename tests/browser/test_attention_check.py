"""The attention check between two agents, by keyboard alone: the participant is asked to move
the robot to the star with the arrow keys, sees the moves left, may reload mid-check and find
it as it was, and goes on to the next agent with Enter; the server records the moves and the
outcome. A check whose moves run out says only that it is recorded, and the participant goes on
all the same; the arrow buttons by the grid move the robot too."""

from __future__ import annotations

import json
from collections.abc import Iterator

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

CHECKS = """
[attention_checks]
enabled = true
size = 5
start = [4, 0]
star = [0, 4]
moves = 10
"""


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    config = study_toml(
        mode="lab",
        domains_toml=domain_toml("navigation", "wall"),
        learners='["cloning"]',
        agents=2,
        allow_anonymous=True,
        tutorial=False,
    )
    yield from run_live_server(tmp_path_factory.mktemp("attention-check"), config + CHECKS)


def reach_the_check(page: Page, server: LiveServer) -> Study:
    page.goto(f"{server.url}/study")
    study = Study(page)
    page.click('[data-action="agree"]')
    page.click('[data-action="start"]')
    expect(study.teach).to_be_visible(timeout=WAIT_MS)
    study.focus()
    for task in range(page.locator(".task").count()):
        study.demonstrate(task)
    study.press("n")
    expect(page.locator('[data-action="confirm-next"]')).to_be_visible()
    study.press("Enter")
    expect(page.locator('[data-testid="attention-check"]')).to_be_visible(timeout=WAIT_MS)
    return study


def press_and_wait(page: Page, key: str, moves_left: int) -> None:
    page.keyboard.press(key)
    expect(page.locator(".check-status")).to_have_text(
        f"{moves_left} {'move' if moves_left == 1 else 'moves'} left.", timeout=WAIT_MS
    )


def robot_at(page: Page, row: int, column: int) -> None:
    expect(page.locator(".check-board")).to_have_attribute(
        "aria-label",
        f"A 5 by 5 grid: the robot is in row {row}, column {column}; the star is in row 1, "
        "column 5.",
        timeout=WAIT_MS,
    )


def checks_of(server: LiveServer) -> list[tuple[str, str]]:
    return [
        (row.status, " ".join(json.loads(row.moves)))
        for row in server.query("SELECT status, moves FROM attention_checks ORDER BY id")
    ]


def test_the_check_is_done_by_keyboard_and_survives_a_reload(
    page: Page, server: LiveServer
) -> None:
    watch = Watch(server.url).attach(page)
    study = reach_the_check(page, server)
    expect(page.locator("h1")).to_have_text("Move the robot to the star using the arrow keys")
    expect(page.locator(".check-status")).to_have_text("10 moves left.")
    expect(page.locator('[data-action="after-check"]')).to_have_count(0)  # until it is over
    robot_at(page, 5, 1)
    press_and_wait(page, "ArrowUp", 9)
    press_and_wait(page, "ArrowUp", 8)
    robot_at(page, 3, 1)
    # The arrow keys never scroll the page.
    assert page.evaluate("window.scrollY") == 0
    page.reload()
    expect(page.locator('[data-testid="attention-check"]')).to_be_visible(timeout=WAIT_MS)
    expect(page.locator(".check-status")).to_have_text("8 moves left.")
    robot_at(page, 3, 1)
    for left, key in enumerate(["ArrowUp", "ArrowUp", "ArrowRight", "ArrowRight", "ArrowRight"]):
        press_and_wait(page, key, 7 - left)
    page.keyboard.press("ArrowRight")
    status = page.locator(".check-status")
    expect(status).to_contain_text("The robot reached the star", timeout=WAIT_MS)
    expect(status).to_contain_text("this is recorded")
    expect(page.locator('[data-action="after-check"]')).to_be_focused()
    assert checks_of(server) == [("passed", "UP UP UP UP RIGHT RIGHT RIGHT RIGHT")]
    # A key pressed now moves nothing.
    page.keyboard.press("ArrowLeft")
    page.keyboard.press("Enter")
    expect(page.locator('[data-action="begin-agent"]')).to_be_visible(timeout=WAIT_MS)
    page.keyboard.press("Enter")
    expect(study.teach).to_have_attribute("data-kind", "study", timeout=WAIT_MS)
    assert checks_of(server) == [("passed", "UP UP UP UP RIGHT RIGHT RIGHT RIGHT")]
    watch.check()


def test_a_check_whose_moves_run_out_is_recorded_and_the_participant_goes_on(
    page: Page, server: LiveServer
) -> None:
    reach_the_check(page, server)
    # The arrow buttons by the grid move the robot as the keys do.
    page.get_by_role("button", name="Left").click()
    expect(page.locator(".check-status")).to_have_text("9 moves left.", timeout=WAIT_MS)
    for left in range(8, 0, -1):
        press_and_wait(page, "ArrowLeft", left)  # into the edge: the robot stays
    robot_at(page, 5, 1)
    page.keyboard.press("ArrowDown")
    status = page.locator(".check-status")
    expect(status).to_contain_text("That was the last move", timeout=WAIT_MS)
    expect(status).not_to_contain_text("fail")
    page.keyboard.press("Enter")
    expect(page.locator('[data-action="begin-agent"]')).to_be_visible(timeout=WAIT_MS)
    assert checks_of(server)[-1] == ("failed", " ".join(["LEFT"] * 9 + ["DOWN"]))
