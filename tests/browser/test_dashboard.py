"""The experimenter excludes a participant from the dashboard with a reason, and includes them
again; the database keeps both reasons. The replay's pause sign, the capacity's tiles in a
small window, and the deployment's servers with their machines and loads."""

from __future__ import annotations

import re
from collections.abc import Iterator

import pytest
from playwright.sync_api import Page, expect

from server.app.storage.models import utcnow
from tests.browser.conftest import (
    LiveServer,
    Watch,
    admin_login,
    domain_toml,
    run_live_server,
    study_toml,
)

pytestmark = pytest.mark.browser


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    config = study_toml(
        mode="lab", domains_toml=domain_toml("navigation", "wall"), learners='["cloning"]', agents=1
    )
    yield from run_live_server(tmp_path_factory.mktemp("dashboard-study"), config)


def test_exclude_and_include_again_with_the_reasons(page: Page, server: LiveServer) -> None:
    arrived = page.request.post(f"{server.url}/api/arrivals", data={})
    assert arrived.status == 201, arrived.text()
    watch = Watch(server.url).attach(page)
    admin_login(page, server, "/dashboard")
    row = page.locator("#participants tr[data-participant]")
    expect(row).to_have_count(1)
    row.click()
    detail = page.locator("#detail")
    # No reason, no exclusion.
    page.click('#detail [data-action="exclude"]')
    expect(detail.locator("form.exclusion .form-error")).to_have_text(
        "Give a reason: it is kept with the data."
    )
    page.fill("#exclusion-reason", "pressed keys at random")
    page.click('#detail [data-action="exclude"]')
    expect(row.locator(".badge.excluded")).to_have_count(1)
    expect(detail).to_contain_text("Excluded: pressed keys at random")
    (marked,) = server.query("SELECT excluded_at, exclusion_reason FROM participants")
    assert marked.excluded_at is not None and marked.exclusion_reason == "pressed keys at random"
    page.fill("#exclusion-reason", "the log shows real teaching")
    page.click('#detail [data-action="include"]')
    expect(row.locator(".badge.excluded")).to_have_count(0)
    expect(detail).to_contain_text("Included in the analysis.")
    history = server.query(
        "SELECT status, note FROM status_changes WHERE status IN ('excluded', 'included') "
        "ORDER BY id"
    )
    assert [(r.status, r.note) for r in history] == [
        ("excluded", "pressed keys at random"),
        ("included", "the log shows real teaching"),
    ]
    watch.check()


def test_the_replay_s_play_button_draws_its_pause_sign(page: Page, server: LiveServer) -> None:
    """Debian's fonts lack the pause glyph: the button draws it."""
    arrived = page.request.post(f"{server.url}/api/arrivals", data={})
    assert arrived.status == 201, arrived.text()
    for seq, path, body in ((1, "consent", {"agree": True}), (2, "start", {})):
        answer = page.request.post(
            f"{server.url}/api/participant/{path}", data={"seq": seq, **body}
        )
        assert answer.status == 200, answer.text()
    session = answer.json()["participant"]["current_session_id"]
    for seq, move in ((3, "UP"), (4, "DOWN"), (5, "LEFT")):
        moved = page.request.post(
            f"{server.url}/api/sessions/{session}/move", data={"seq": seq, "action": move}
        )
        assert moved.status == 200, moved.text()
    watch = Watch(server.url).attach(page)
    admin_login(page, server, "/dashboard")
    page.locator("#participants tr[data-participant]").last.click()
    page.locator('#detail [data-action="replay"]').first.click()
    play = page.locator('#replay [data-action="play"]')
    expect(play.locator('svg[data-icon="play"]')).to_have_count(1)
    play.click()
    expect(play.locator('svg[data-icon="pause"] rect')).to_have_count(2)
    expect(play).to_have_text("Pause")
    assert "⏸" not in play.inner_text()
    expect(play.locator('svg[data-icon="play"]')).to_have_count(1, timeout=10_000)  # the end
    watch.check()


def test_a_row_of_capacity_figures_lines_up_in_a_small_window(
    page: Page, server: LiveServer
) -> None:
    """At 1024x640 some tiles' labels take two lines: each row's figures still share a line."""
    page.set_viewport_size({"width": 1024, "height": 640})
    admin_login(page, server, "/dashboard")
    tiles = page.locator("#queue > div")
    expect(tiles).to_have_count(7)
    rows: dict[int, list[float]] = {}
    for tile in tiles.all():
        box, figure = tile.bounding_box(), tile.locator("dd").bounding_box()
        assert box is not None and figure is not None
        rows.setdefault(round(box["y"]), []).append(figure["y"])
    assert len(rows) >= 2  # the tiles wrap at this width
    for tops in rows.values():
        assert max(tops) - min(tops) < 1, rows


def test_the_dashboard_shows_each_server_its_machine_and_its_load(
    page: Page, server: LiveServer
) -> None:
    """Another server on the same machine, beating, with three updates running: listed beside
    this one, with the same machine and its load."""
    (this,) = server.query("SELECT machine, cores FROM servers WHERE stopped_at IS NULL")
    server.query(
        "INSERT INTO servers (name, host, pid, started_at, heartbeat_at, update_slots, "
        "updates_running, updates_completed, updates_failed, machine, cores) VALUES "
        "('neighbour-7-abcdef', 'neighbour', 7, :now, :now, 1, 3, 41, 2, :machine, :cores)",
        now=utcnow().strftime("%Y-%m-%d %H:%M:%S.%f"),  # as SQLite's rows store it
        machine=this.machine,
        cores=this.cores,
    )
    watch = Watch(server.url).attach(page)
    admin_login(page, server, "/dashboard")
    rows = page.locator("#servers tbody tr")
    expect(rows).to_have_count(2)
    neighbour = page.locator('#servers tr[data-server="neighbour-7-abcdef"]')
    cells = neighbour.locator("td")
    expect(cells).to_have_text(
        ["neighbour-7-abcdef", f"neighbour, machine 1 ({this.cores} cores)", "live",
         re.compile(r"\S"), re.compile(r"\S"), "1", "3", "41", "2", "not timed yet"],
        timeout=10_000,
    )  # fmt: skip
    machines = {row.get_attribute("data-machine") for row in rows.all()}
    assert machines == {"1"}
    server.query("DELETE FROM servers WHERE name = 'neighbour-7-abcdef'")
    watch.check()
