"""The dashboard's words and curves: singular and plural counts, a learning curve whose "100%"
label is inside the drawing, and an agent with no episode that says so instead of drawing an
empty axis."""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest
from playwright.sync_api import APIRequestContext, Page, expect

from tests.browser.conftest import (
    WAIT_MS,
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
        mode="lab",
        domains_toml=domain_toml("navigation", "wall"),
        learners='["cloning"]',
        agents=2,
        tutorial=False,
    )
    yield from run_live_server(tmp_path_factory.mktemp("dashboard-wording"), config)


def one_episode(request: APIRequestContext, server: LiveServer) -> tuple[int, int]:
    """A participant whose first agent has one episode (a demonstration of two moves, or one
    when the first reaches the goal) and whose second has none; returns the first agent's
    session and its number of actions."""
    arrived = request.post(f"{server.url}/api/arrivals", data={})
    assert arrived.status == 201, arrived.text()
    seq = arrived.json()["participant"]["next_seq"]
    steps: list[tuple[str, dict[str, object]]] = [
        ("participant/consent", {"agree": True}),
        ("participant/start", {}),
    ]
    session = 0
    for path, body in steps:
        answer = request.post(f"{server.url}/api/{path}", data={"seq": seq, **body})
        assert answer.status == 200, answer.text()
        seq = answer.json()["participant"]["next_seq"]
        session = answer.json()["participant"]["current_session_id"]
    for path, body in (
        ("mode", {"mode": "demonstrate"}),
        ("move", {"action": "UP"}),
        ("move", {"action": "DOWN"}),
        ("mode", {"mode": "idle"}),
    ):
        answer = request.post(
            f"{server.url}/api/sessions/{session}/{path}", data={"seq": seq, **body}
        )
        assert answer.status == 200, answer.text()
        seq = answer.json()["participant"]["next_seq"]
    return session, int(answer.json()["session"]["actions"])


def test_counts_curves_and_an_agent_with_no_episode(page: Page, server: LiveServer) -> None:
    session, actions = one_episode(page.request, server)
    assert actions in (1, 2)
    deadline = time.monotonic() + WAIT_MS / 1000
    while (
        server.query(
            "SELECT count(*) AS n FROM learner_updates WHERE session_id = :s AND status = 'done'",
            s=session,
        )[0].n
        < 2
    ):
        assert time.monotonic() < deadline, "the learner updates did not finish"
        time.sleep(0.2)
    watch = Watch(server.url).attach(page)
    admin_login(page, server, "/dashboard")
    expect(page.locator("#summary .badge").first).to_have_text("1 participant")
    page.locator("#participants tr[data-participant]").click()
    first = page.locator(f'#detail .session-card[data-session="{session}"]')
    expect(first).to_contain_text(
        "1 episode, 2 actions" if actions == 2 else "1 episode, 1 action,"
    )
    # The curve of the agent with one episode (both its updates done): its labels inside it.
    expect(first.locator('svg.curve[data-points="2"]')).to_have_count(1)
    outside = page.evaluate(
        """(session) => {
          const svg = document.querySelector(`.session-card[data-session="${session}"] svg.curve`);
          const box = svg.getBoundingClientRect();
          return [...svg.querySelectorAll("text")]
            .filter((t) => { const b = t.getBoundingClientRect();
              return b.left < box.left || b.right > box.right || b.top < box.top || b.bottom > box.bottom; })
            .map((t) => t.textContent);
        }""",
        session,
    )
    assert outside == []
    expect(first.locator("svg.curve text", has_text="100%")).to_have_count(1)
    # The second agent has no episode: it says so, with no empty axis.
    second = page.locator("#detail .session-card").nth(1)
    expect(second).to_contain_text("0 episodes, 0 actions")
    expect(second.locator(".no-curve")).to_have_text(
        "No episode yet: the curve starts with the first one."
    )
    expect(second.locator("svg.curve")).to_have_count(0)
    watch.check()
