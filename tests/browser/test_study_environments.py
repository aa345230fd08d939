"""A study's own environment drawn on the page: the vineyard study (server/examples) adds a
terrain, vines, and a machine, the trellis, with colours of its own. The participant's page and
the dashboard's replay draw them in the study's colours with their names (a pattern and an
initial on every vines cell, a machine picture with its initial and name for the trellis), the
legend names them, the robot picks the trellis up by keyboard and enters the vines with it, and
axe finds nothing wrong with the page. A gravity study's own colour gets its colour, a pattern
and its letter as the built-in colours do."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from playwright.sync_api import Locator, Page, expect

from server import domains
from tests.browser.conftest import (
    FAST_LEARNERS,
    WAIT_MS,
    LiveServer,
    Study,
    Watch,
    admin_login,
    axe_violations,
    domain_toml,
    moves_to,
    run_live_server,
    study_toml,
)

pytestmark = pytest.mark.browser

EXAMPLES = Path(__file__).resolve().parents[2] / "server" / "examples"
VINES = "#6b8e23"
TRELLIS = "#8b4513"
# The resolved fill of an SVG shape: a colour, or the colour of the pattern it is filled with
# (the pattern's first rect, its ground).
GROUND = """(node) => {
  const fill = node.getAttribute("fill");
  const match = /^url\\(#(.+)\\)$/.exec(fill);
  return match ? document.getElementById(match[1]).querySelector("rect").getAttribute("fill") : fill;
}"""


def vineyard_toml() -> str:
    """The example study as it is, but in the lab (no MTurk ids), one fast learner, no
    tutorial: the page opens on the vineyard."""
    text = (EXAMPLES / "vineyard-study.toml").read_text(encoding="utf-8")
    for old, new in (
        ('learners = ["bam", "cloning"]', 'learners = ["cloning"]\nallow_anonymous = true'),
        ('[completion]\nmode = "mturk"', '[completion]\nmode = "lab"'),
    ):
        assert old in text, old
        text = text.replace(old, new)
    return f"{text}\n[tutorial]\nenabled = false\n{FAST_LEARNERS}"


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    yield from run_live_server(tmp_path_factory.mktemp("vineyard-study"), vineyard_toml())


def path_to(environment: str, state: int, target: int) -> list[str]:
    """The fewest moves from ``state`` to ``target`` under the true dynamics."""
    return moves_to(environment, state, lambda s: s == target, f"state {target}")


def trellis_state() -> int:
    """The state on the trellis's cell, carrying it."""
    env = domains.make("vineyard")
    (trellis,) = [m for m in env.layout["machines"] if m["machine"] == "trellis"]
    return env.state_of(trellis["row"], trellis["column"], env.feature_names.index("trellis"))


def open_vineyard(page: Page, server: LiveServer) -> Study:
    page.goto(f"{server.url}/study")
    page.click('[data-action="agree"]')
    page.click('[data-action="start"]')
    study = Study(page)
    expect(study.teach).to_have_attribute("data-environment", "vineyard", timeout=WAIT_MS)
    return study


def check_drawing(grid: Locator) -> None:
    """The vines cells and the trellis in the study's colours, with their initials and names."""
    env = domains.make("vineyard")
    vines = [
        (r, c)
        for r, row in enumerate(env.layout["terrain"])
        for c, t in enumerate(row)
        if t == "vines"
    ]
    assert len(vines) == 8
    cells = grid.locator("rect.cell-vines")
    expect(cells).to_have_count(len(vines))
    for index in range(cells.count()):
        cell = cells.nth(index)
        assert cell.evaluate(GROUND) == VINES
        expect(cell.locator("title")).to_have_text("Vines")
    # The pattern over the colour is none of the built-in terrains' patterns.
    own_pattern = str(cells.first.get_attribute("fill"))
    for terrain in ("dirt", "soil", "grass", "crops"):
        other = grid.locator(f"rect.cell-{terrain}").first
        assert other.get_attribute("fill") != own_pattern
    initials = grid.locator('g.cell-initial[data-terrain="vines"]')
    expect(initials).to_have_count(len(vines))
    expect(initials.locator("text")).to_have_text(["V"] * len(vines))
    expect(grid.locator("rect.cell-soil").first).not_to_have_attribute("data-colour", VINES)
    # The trellis: a machine in its colour, its initial and its name under it.
    trellis = grid.locator('g.machine[data-machine="trellis"]')
    expect(trellis).to_have_count(1)
    expect(trellis.locator("title")).to_have_text("Trellis")
    assert trellis.locator("rect.machine-body").evaluate(GROUND) == TRELLIS
    expect(trellis.locator(".kind-initial text")).to_have_text("T")
    expect(trellis.locator(":scope > text")).to_have_text("Trellis")
    # The built-in machines keep their own pictures and names.
    for machine, name in (("plow", "Plow"), ("sprinkler", "Sprinkler"), ("harvester", "Harvester")):
        built_in = grid.locator(f'g.machine[data-machine="{machine}"]')
        expect(built_in.locator(f"g.machine-{machine}")).to_have_count(1)
        expect(built_in.locator(":scope > text")).to_have_text(name)
        expect(built_in.locator("title")).to_have_count(0)


def test_the_page_draws_the_vines_and_the_trellis_and_the_robot_takes_it(
    page: Page, server: LiveServer
) -> None:
    watch = Watch(server.url).attach(page)
    study = open_vineyard(page, server)
    check_drawing(page.locator("svg.grid"))
    legend = page.locator(".legend li")
    expect(legend.locator(":scope > span")).to_have_text(
        [
            "Goal of the selected task",
            "Dirt: free",
            "Soil: needs the plow",
            "Grass: needs the sprinkler",
            "Crops: need the harvester",
            "Vines (V): needs the trellis",
            "Trellis (T): the machine for vines",
        ]
    )
    vines_swatch = legend.locator('svg.swatch[data-kind="vines"]')
    assert vines_swatch.locator(":scope > rect").evaluate(GROUND) == VINES
    expect(vines_swatch.locator("text")).to_have_text("V")
    trellis_swatch = legend.locator('svg.swatch[data-kind="trellis"]')
    assert trellis_swatch.locator("rect.machine-body").evaluate(GROUND) == TRELLIS
    expect(page.locator("details.rules")).to_contain_text(
        "Vines can only be entered carrying the trellis."
    )

    # Drive over the trellis with the arrow keys: the robot carries it.
    study.focus()
    agent = page.locator("g.agent")
    for action in path_to("vineyard", study.state(), trellis_state()):
        study.move(action)
    expect(agent).to_have_attribute("data-feature", "trellis")
    badge = agent.locator(".agent-badge .machine-own")
    expect(badge).to_have_count(1)
    assert badge.locator("rect.machine-body").evaluate(GROUND) == TRELLIS
    expect(page.locator(".teach-page")).to_contain_text("Carrying: Trellis")
    # With it, the robot enters the vines field (task 2), as the plow enters the soil.
    env = domains.make("vineyard")
    assert env.tasks[1].name == "Vines field"
    study.select_task(1)
    study.press("d")
    study.wait_for("mode", "demonstrate")
    study.walk_to_goal(1)
    study.wait_for("mode", "idle")  # the demonstration ended at the goal
    row = int(agent.get_attribute("data-row") or -1)
    column = int(agent.get_attribute("data-column") or -1)
    assert env.layout["terrain"][row][column] == "vines"
    expect(page.locator('.task[data-task="1"]')).not_to_have_attribute("data-count", "0")
    watch.check()


def test_the_vineyard_page_has_no_wcag_violation(page: Page, server: LiveServer) -> None:
    open_vineyard(page, server)
    expect(page.locator('g.machine[data-machine="trellis"]')).to_have_count(1)
    assert axe_violations(page) == []


def test_the_dashboard_replays_a_vineyard_session_in_the_study_s_drawing(
    page: Page, server: LiveServer
) -> None:
    arrived = page.request.post(f"{server.url}/api/arrivals", data={})
    assert arrived.status == 201, arrived.text()
    seq = 0
    for path, body in (("consent", {"agree": True}), ("start", {})):
        seq += 1
        answer = page.request.post(
            f"{server.url}/api/participant/{path}", data={"seq": seq, **body}
        )
        assert answer.status == 200, answer.text()
    session = answer.json()["participant"]["current_session_id"]
    view = page.request.get(f"{server.url}/api/sessions/{session}").json()
    assert view["environment"]["name"] == "vineyard"
    start = view["teaching"]["agent"]["state"]
    moves = path_to("vineyard", start, trellis_state())
    for move in moves:
        seq += 1
        moved = page.request.post(
            f"{server.url}/api/sessions/{session}/move", data={"seq": seq, "action": move}
        )
        assert moved.status == 200, moved.text()
    watch = Watch(server.url).attach(page)
    admin_login(page, server, "/dashboard")
    page.locator("#participants tr[data-participant]").last.click()
    page.locator('#detail [data-action="replay"]').first.click()
    replay = page.locator("#replay svg.grid")
    expect(replay).to_have_attribute("data-environment", "vineyard")
    check_drawing(replay)
    page.click('#replay [data-action="last"]')
    agent = replay.locator("g.agent")
    expect(agent).to_have_attribute("data-feature", "trellis")
    expect(agent).to_have_attribute("data-state", str(trellis_state()))
    assert agent.locator(".agent-badge rect.machine-body").evaluate(GROUND) == TRELLIS
    watch.check()


# -- a gravity study with a colour of its own ---------------------------------------------------
GRAVITY_STUDY = """
[environments.sunset]
domain = "gravity"
gravity_colours = { r = "sky blue" }
colours = { "sky blue" = "#56B4E9" }
map = '''
task: Corner = A
start: rows 0, columns 1-4
gravity of orange: north
gravity of sky blue: west
    012345
  0 A.....
  1 .o..r.
  2 ......
  3 ......
'''
"""


@pytest.fixture(scope="module")
def gravity_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    config = study_toml(
        mode="lab",
        domains_toml=GRAVITY_STUDY + domain_toml("gravity", "sunset"),
        learners='["cloning"]',
        agents=1,
        allow_anonymous=True,
        tutorial=False,
    )
    yield from run_live_server(tmp_path_factory.mktemp("sunset-study"), config)


def test_a_study_s_own_gravity_colour_has_its_colour_pattern_and_letter(
    page: Page, gravity_server: LiveServer
) -> None:
    watch = Watch(gravity_server.url).attach(page)
    page.goto(f"{gravity_server.url}/study")
    page.click('[data-action="agree"]')
    page.click('[data-action="start"]')
    expect(Study(page).teach).to_have_attribute("data-environment", "sunset", timeout=WAIT_MS)
    grid = page.locator("svg.grid")
    own = grid.locator("g.gravity-cell.gravity-sky-blue")
    expect(own).to_have_count(1)
    expect(own).to_have_attribute("data-colour", "#56B4E9")
    assert own.locator(":scope > rect").evaluate(GROUND) == "#56B4E9"
    expect(own.locator("text")).to_have_text("S")
    expect(own.locator("title")).to_have_text("sky blue cell")  # the gravity stays hidden
    orange = grid.locator("g.gravity-cell.gravity-orange")
    expect(orange.locator("text")).to_have_text("O")
    assert orange.locator(":scope > rect").get_attribute("fill") != own.locator(
        ":scope > rect"
    ).get_attribute("fill")
    legend = page.locator(".legend li > span")
    expect(legend.filter(has_text="Sky blue")).to_have_text("Sky blue cell (S): sets the gravity")
    expect(page.get_by_test_id("grid-text")).to_contain_text("A sky blue cell (S) at row 2")
    assert axe_violations(page) == []
    watch.check()
