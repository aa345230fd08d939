"""The device check before consent, in Chromium with the keyboard alone: a window large enough
and an arrow key pressed lead to the consent page; a window too small, or no key pressed in the
time given, turn the participant away with a clear page, recorded (status incompatible, with
the reasons). axe finds nothing on either page at 1280x800 and 1024x640."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from playwright.sync_api import Page, expect

from tests.browser.conftest import (
    LiveServer,
    Watch,
    axe_violations,
    domain_toml,
    run_live_server,
    study_toml,
)

pytestmark = pytest.mark.browser

# The time for a key press: long enough for any test that presses one, however slow the machine;
# short where a test waits for it to run out.
KEY_SECONDS, SHORT_KEY_SECONDS = 600, 2
SIZES = [(1280, 800), (1024, 640)]


def device_study(tmp: Path, key_seconds: int) -> Iterator[LiveServer]:
    config = study_toml(
        mode="lab",
        allow_anonymous=True,
        domains_toml=domain_toml("navigation", "two-rooms"),
        learners='["cloning"]',
        agents=1,
    )
    check = f"""
[device_check]
enabled = true
min_width = 1000
min_height = 600
key_seconds = {key_seconds}
"""
    yield from run_live_server(tmp, config + check)


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    yield from device_study(tmp_path_factory.mktemp("device-check"), KEY_SECONDS)


@pytest.fixture(scope="module")
def impatient(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    yield from device_study(tmp_path_factory.mktemp("device-check-short"), SHORT_KEY_SECONDS)


def arrive(page: Page, server: LiveServer, width: int, height: int) -> None:
    page.context.clear_cookies()
    page.set_viewport_size({"width": width, "height": height})
    page.goto(f"{server.url}/study")
    expect(page.locator("h1")).to_have_text("Before you start: a check of your device")


def participant_row(page: Page, server: LiveServer) -> tuple[str, str | None]:
    participant = page.request.get(f"{server.url}/api/participant").json()
    (row,) = server.query(
        "SELECT p.status, s.note FROM participants p JOIN status_changes s"
        " ON s.participant_id = p.id WHERE p.id = :p ORDER BY s.id DESC LIMIT 1",
        p=participant["participant_id"],
    )
    return row.status, row.note


@pytest.mark.parametrize(("width", "height"), SIZES)
def test_an_arrow_key_in_a_large_enough_window_leads_to_consent(
    page: Page, server: LiveServer, width: int, height: int
) -> None:
    watch = Watch(server.url).attach(page)
    arrive(page, server, width, height)
    size = page.locator('[data-device="size"]')
    expect(size).to_have_attribute("data-enough", "true")
    expect(size).to_contain_text(f"{width} \u00d7 {height}")
    assert axe_violations(page) == []
    page.keyboard.press("ArrowLeft")
    expect(page.locator('[data-action="agree"]')).to_be_visible()
    status, _ = participant_row(page, server)
    assert status == "arrived"
    (event,) = server.query(
        "SELECT kind FROM events WHERE participant_id = (SELECT max(id) FROM participants)"
    )
    assert event.kind == "device_check"
    page.keyboard.press("Tab")  # the keyboard alone: Tab to the consent text, its answers
    page.locator('[data-action="agree"]').focus()
    page.keyboard.press("Enter")
    expect(page.locator('[data-action="start"]')).to_be_visible()
    watch.check()


def test_a_window_too_small_is_turned_away(page: Page, server: LiveServer) -> None:
    watch = Watch(server.url).attach(page)
    arrive(page, server, 900, 560)
    expect(page.locator('[data-device="size"]')).to_have_attribute("data-enough", "false")
    page.keyboard.press("ArrowUp")
    expect(page.locator("h1")).to_have_text("Sorry: this study cannot run on your device")
    expect(page.locator('[data-device="problems"]')).to_contain_text(
        "your window was 900 \u00d7 560 pixels, smaller than the 1000 \u00d7 600"
    )
    status, note = participant_row(page, server)
    assert status == "incompatible"
    assert note is not None and "the window is 900x560" in note and "Chrome" in note
    # A reload shows the same page; the flow has ended.
    page.reload()
    expect(page.locator("h1")).to_have_text("Sorry: this study cannot run on your device")
    watch.check()


@pytest.mark.parametrize(("width", "height"), SIZES)
def test_a_page_with_no_key_press_is_turned_away(
    page: Page, impatient: LiveServer, width: int, height: int
) -> None:
    watch = Watch(impatient.url).attach(page)
    arrive(page, impatient, width, height)
    # Nothing pressed: the check ends after its time and turns the participant away.
    expect(page.locator("h1")).to_have_text(
        "Sorry: this study cannot run on your device", timeout=SHORT_KEY_SECONDS * 1000 + 60_000
    )
    expect(page.locator('[data-device="problems"]')).to_contain_text("no arrow key was pressed")
    status, note = participant_row(page, impatient)
    assert status == "incompatible"
    assert note is not None and note.startswith("no arrow key was pressed")
    assert axe_violations(page) == []
    watch.check()


def test_a_participant_without_arrow_keys_can_say_so(page: Page, server: LiveServer) -> None:
    arrive(page, server, 1280, 800)
    # Tab reaches the button, Enter presses it (no arrow key involved).
    button = page.locator('[data-action="no-arrow-keys"]')
    for _ in range(10):
        page.keyboard.press("Tab")
        if page.evaluate("document.activeElement.dataset.action") == "no-arrow-keys":
            break
    expect(button).to_be_focused()
    page.keyboard.press("Enter")
    expect(page.locator("h1")).to_have_text("Sorry: this study cannot run on your device")
    status, _ = participant_row(page, server)
    assert status == "incompatible"


@pytest.mark.parametrize(
    ("width", "height", "verdict"),
    [(1280, 800, "ready"), (1024, 640, "ready"), (900, 560, "do-not-accept")],
)
def test_the_mturk_preview_tells_a_worker_whether_to_accept(
    page: Page, server: LiveServer, width: int, height: int, verdict: str
) -> None:
    """The HIT's preview checks the device (nothing is recorded: a preview creates nothing), so
    that a worker whose device cannot take part does not accept the HIT."""
    watch = Watch(server.url).attach(page)
    before = server.query("SELECT count(*) AS n FROM participants")[0].n
    page.set_viewport_size({"width": width, "height": height})
    page.goto(f"{server.url}/study?assignmentId=ASSIGNMENT_ID_NOT_AVAILABLE&hitId=H1")
    expect(page.locator("h2#device-preview-title")).to_be_visible()
    page.keyboard.press("ArrowRight")
    expect(page.locator('[data-device="verdict"]')).to_have_attribute("data-verdict", verdict)
    if verdict == "do-not-accept":
        expect(page.locator('[data-device="verdict"]')).to_contain_text("do not accept this HIT")
    assert axe_violations(page) == []
    assert server.query("SELECT count(*) AS n FROM participants")[0].n == before
    watch.check()
