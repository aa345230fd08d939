"""The live views in Chromium, with the keyboard alone: the funnel changes as participants
arrive, leave and wait for an update (each count the database's), the one-way mirror follows a
simulated participant's moves, the agent's try and its +/-, from agent to agent, and the live
curves move as agents are evaluated; axe finds nothing on either page at 1280x800 and 1024x640.

The participants are simulated over the JSON API (as ``bam-study simulate`` does); the learner
updates run behind a gate, so that one can be held pending as long as the test needs."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from playwright.sync_api import Page, expect

from tests.browser.conftest import (
    WAIT_MS,
    LiveServer,
    Watch,
    admin_login,
    axe_violations,
    domain_toml,
    run_live_server,
    study_toml,
)
from tests.support.server import Gated
from tests.support.server import Participant as ApiParticipant

pytestmark = pytest.mark.browser

SIZES = [(1280, 800), (1024, 640)]


@pytest.fixture(scope="module")
def gate() -> Iterator[Gated]:
    gated = Gated()
    yield gated
    gated.shutdown()


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory, gate: Gated) -> Iterator[LiveServer]:
    config = study_toml(
        mode="lab",
        allow_anonymous=True,
        domains_toml=domain_toml("navigation", "two-rooms"),
        learners='["cloning", "bam"]',
        agents=2,
    )
    yield from run_live_server(tmp_path_factory.mktemp("live"), config, executor=gate)


def arrive(server: LiveServer) -> ApiParticipant:
    client = httpx.Client(base_url=server.url, timeout=120)
    answer = client.post("/api/arrivals", json={})
    assert answer.status_code == 201, answer.text
    return ApiParticipant(client, answer.json()["token"])


def in_tutorial(server: LiveServer) -> tuple[ApiParticipant, int]:
    participant = arrive(server)
    participant.act("/api/participant/consent", agree=True)
    session = participant.act("/api/participant/start")["participant"]["current_session_id"]
    participant.act(f"/api/sessions/{session}/open")
    return participant, int(session)


def stage_count(page: Page, stage: str, count: int) -> None:
    expect(page.locator(f'#funnel li[data-stage="{stage}"]')).to_have_attribute(
        "data-count", str(count), timeout=WAIT_MS
    )


def status_counts(server: LiveServer) -> dict[str, int]:
    rows = server.query("SELECT status, count(*) AS n FROM participants GROUP BY status")
    return {row.status: row.n for row in rows}


def shown_counts(page: Page) -> dict[str, int]:
    items = page.locator("#funnel li")
    return {
        str(items.nth(i).get_attribute("data-stage")): int(
            str(items.nth(i).get_attribute("data-count"))
        )
        for i in range(items.count())
    }


def test_the_funnel_changes_as_participants_arrive_leave_and_wait(
    page: Page, server: LiveServer, gate: Gated
) -> None:
    watch = Watch(server.url).attach(page)
    admin_login(page, server, "/dashboard/live")
    expect(page.locator("#funnel-at")).to_have_attribute("data-live", "on", timeout=WAIT_MS)
    before = shown_counts(page)
    assert before["consent"] == status_counts(server).get("arrived", 0)

    leaving = arrive(server)
    stage_count(page, "consent", before["consent"] + 1)
    assert shown_counts(page)["consent"] == status_counts(server)["arrived"]

    waiting, session = in_tutorial(server)
    stage_count(page, "tutorial", before["tutorial"] + 1)
    expect(page.locator('#people tr[data-stage="tutorial"]')).to_have_count(before["tutorial"] + 1)

    # Its agent's turn while its learner is still updating (the update held at the gate).
    gate.gate.clear()
    try:
        base = f"/api/sessions/{session}"
        waiting.act(f"{base}/mode", mode="demonstrate")
        waiting.act(f"{base}/move", action="LEFT")
        waiting.act(f"{base}/end-episode")
        waiting.act(f"{base}/mode", mode="agent")
        stage_count(page, "updating", before["updating"] + 1)
        stage_count(page, "tutorial", before["tutorial"])
        expect(page.locator('#updates [data-queue="pending"] dd')).not_to_have_text("0")

        leaving.act("/api/participant/consent", agree=False)  # leaves
        stage_count(page, "declined", before["declined"] + 1)
        stage_count(page, "consent", before["consent"])
        shown = shown_counts(page)
        database = status_counts(server)
        assert shown["declined"] == database["declined"]
        assert shown["consent"] == database.get("arrived", 0)
        for width, height in SIZES:
            page.set_viewport_size({"width": width, "height": height})
            assert axe_violations(page) == [], (width, height)
    finally:
        gate.gate.set()
    stage_count(page, "updating", before["updating"])
    stage_count(page, "tutorial", before["tutorial"] + 1)
    watch.check()


def test_the_mirror_follows_a_participant_and_the_curves_move(
    page: Page, server: LiveServer, screenshot_dir: Path
) -> None:
    watch = Watch(server.url).attach(page)
    participant, session = in_tutorial(server)
    (row,) = server.query("SELECT participant_id FROM learning_sessions WHERE id = :s", s=session)
    admin_login(page, server, "/dashboard/live")
    link = page.locator(
        f'#people tr[data-participant="{row.participant_id}"] a[data-action="watch"]'
    )
    expect(link).to_be_visible(timeout=WAIT_MS)
    link.focus()
    page.keyboard.press("Enter")
    page.wait_for_url(f"**/dashboard/live/participants/{row.participant_id}")
    board = page.locator("#mirror-board")
    expect(board).to_have_attribute("data-agent", "tutorial", timeout=WAIT_MS)

    base = f"/api/sessions/{session}"
    start = int(str(board.get_attribute("data-state")))
    moved = None
    for action in ("LEFT", "RIGHT", "UP", "DOWN"):
        answer = participant.act(f"{base}/move", action=action)
        if answer["outcome"]["next_state"] != start:
            moved = answer["outcome"]["next_state"]
            break
    assert moved is not None
    expect(board).to_have_attribute("data-state", str(moved), timeout=WAIT_MS)
    # Watching left no trace: every event and sequence number of the participant is one of
    # their own requests.
    (trace,) = server.query(
        "SELECT p.next_seq, (SELECT count(*) FROM events e WHERE e.participant_id = p.id) AS n"
        " FROM participants p WHERE p.id = :p",
        p=row.participant_id,
    )
    assert trace.next_seq == participant.seq and trace.n == participant.seq - 1

    # A demonstration, an update, the agent's try and its +/-.
    participant.act(f"{base}/mode", mode="demonstrate")
    participant.act(f"{base}/move", action="LEFT")
    participant.act(f"{base}/end-episode")
    participant.act(f"{base}/mode", mode="agent")
    expect(board).to_have_attribute("data-mode", "agent", timeout=WAIT_MS)
    for _ in range(2):
        stepped = participant.post(f"{base}/agent-step")
        assert stepped.status_code == 200, stepped.text
        participant.seq = stepped.json()["participant"]["next_seq"]
        if stepped.json()["outcome"].get("episode_ended"):
            break
    participant.act(f"{base}/feedback", feedback=1)
    participant.act(f"{base}/feedback", feedback=-1)
    expect(page.locator("#mirror-try .feedback-mark.good")).to_have_count(1, timeout=WAIT_MS)
    expect(page.locator("#mirror-try .feedback-mark.bad")).to_have_count(1)
    expect(page.locator("#mirror-curve")).not_to_have_attribute("data-points", "0", timeout=WAIT_MS)
    for width, height in SIZES:
        page.set_viewport_size({"width": width, "height": height})
        assert axe_violations(page) == [], (width, height)
    page.screenshot(path=str(screenshot_dir / "live-mirror.png"))

    # On to the first study agent: the mirror follows.
    if participant.get(base)["teaching"]["mode"] == "agent":
        participant.act(f"{base}/mode", mode="idle")
    participant.act(f"{base}/finish")
    expect(board).to_have_attribute("data-agent", "1", timeout=WAIT_MS)
    expect(page.locator("#mirror-stage")).to_contain_text("Teaching agent 1 of 2")

    # The live curves: this agent's evaluation appears, then moves with its next episode.
    page.goto(f"{server.url}/dashboard/live")
    figure = page.locator('#curves figure[data-environment="two-rooms"]')
    expect(figure).to_be_visible(timeout=WAIT_MS)
    line = figure.locator("polyline.chart-line")
    expect(line).to_have_count(1, timeout=WAIT_MS)
    points = line.get_attribute("points")
    current = participant.get("/api/participant")["current_session_id"]
    study_base = f"/api/sessions/{current}"
    participant.act(f"{study_base}/open")
    participant.act(f"{study_base}/mode", mode="demonstrate")
    participant.act(f"{study_base}/move", action="LEFT")
    participant.act(f"{study_base}/end-episode")
    expect(line).not_to_have_attribute("points", str(points), timeout=WAIT_MS)
    expect(figure.locator(".chart-legend li")).to_contain_text("1 session")
    for width, height in SIZES:
        page.set_viewport_size({"width": width, "height": height})
        assert axe_violations(page) == [], (width, height)
    page.screenshot(path=str(screenshot_dir / "live-dashboard.png"), full_page=True)
    watch.check()
