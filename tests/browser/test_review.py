"""The experimenter reviews a worker's submitted HIT from the dashboard: approves it with
feedback and pays a bonus; the local MTurk replica's HIT page shows both. Each form's error is
by its own buttons; every time on the dashboard and the replica is written one way, with its
zone; the dashboard counts participants by status and by domain in separate rows."""

from __future__ import annotations

import re
from collections.abc import Iterator

import pytest
from playwright.sync_api import Browser, Page, expect

from tests.browser.conftest import (
    WAIT_MS,
    LiveServer,
    Watch,
    admin_login,
    domain_toml,
    run_live_server,
    study_frame,
    study_toml,
)
from tests.browser.test_submit_target import complete_over_the_api

pytestmark = pytest.mark.browser


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    config = study_toml(
        mode="mturk",
        domains_toml=domain_toml("navigation", "wall"),
        learners='["cloning"]',
        agents=1,
        tutorial=False,
    )
    yield from run_live_server(tmp_path_factory.mktemp("review-study"), config)


TIME = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d UTC$")


def submit_a_hit(page: Page, server: LiveServer, worker: str) -> None:
    """Worker ``worker`` accepts the replica's HIT, completes the study and submits it."""
    admin_login(page, server, "/mturk")
    page.fill("#workerId", worker)
    page.click('[data-action="accept"]')
    page.wait_for_url(f"{server.url}/mturk/work/*")
    study_frame(page)
    token = next(c["value"] for c in page.context.cookies() if c["name"] == "bam_participant")
    complete_over_the_api(server, token)
    page.reload()
    frame = study_frame(page)
    frame.locator('[data-action="submit-hit"]').click(timeout=WAIT_MS)
    page.wait_for_url(f"{server.url}/mturk/externalSubmit")


def test_approve_and_pay_a_bonus_from_the_dashboard(page: Page, server: LiveServer) -> None:
    watch = Watch(server.url).attach(page)
    submit_a_hit(page, server, "WREVIEW")

    page.goto(f"{server.url}/dashboard")
    page.locator("#participants tr[data-participant]").click()
    detail = page.locator("#detail")
    # A rejection without feedback is stopped on the page.
    detail.locator('[data-action="reject"]').click()
    expect(detail.locator("#review-error")).to_have_text(
        "A rejection needs feedback: the participant is shown why."
    )
    page.get_by_label("Feedback to the worker (needed to reject)").fill("Thank you!")
    # Approve and Pay ask first: declined, nothing is sent; accepted, it goes.
    asked: list[str] = []
    page.once("dialog", lambda dialog: (asked.append(dialog.message), dialog.dismiss()))
    detail.locator('[data-action="approve"]').click()
    expect(detail.locator('[data-action="approve"]')).to_be_enabled()
    assert server.query("SELECT id FROM reviews") == []
    page.on("dialog", lambda dialog: (asked.append(dialog.message), dialog.accept()))
    detail.locator('[data-action="approve"]').click()
    expect(detail.locator('[data-review="approved"]')).to_contain_text("Thank you!")
    expect(detail.locator('[data-action="approve"]')).to_have_count(0)
    page.get_by_label("Bonus (USD)").fill("1.25")
    page.get_by_label("Reason, shown to the participant").fill("Taught every task")
    detail.locator('[data-action="bonus"]').click()
    expect(detail.locator('.bonuses li[data-amount="1.25"]')).to_contain_text("Taught every task")

    (review,) = server.query("SELECT decision, message, backend FROM reviews")
    assert tuple(review) == ("approved", "Thank you!", "mturk-replica")
    assert [m.split("?")[0] for m in asked] == [
        "Approve this submission",
        "Approve this submission",
        "Pay a bonus of 1.25",
    ]
    (bonus,) = server.query("SELECT amount_cents, reason FROM bonuses")
    assert tuple(bonus) == (125, "Taught every task")

    page.goto(f"{server.url}/mturk")
    row = page.locator('#assignments tr[data-worker="WREVIEW"]')
    expect(row).to_have_attribute("data-status", "approved")
    expect(row).to_contain_text("Thank you!")
    expect(page.locator('#bonuses tr[data-amount="1.25"]')).to_contain_text("Taught every task")
    watch.check()


def test_each_form_s_error_is_by_its_own_buttons(page: Page, server: LiveServer) -> None:
    submit_a_hit(page, server, "WERRORS")
    page.goto(f"{server.url}/dashboard")
    page.locator('#participants tr[data-participant]:has-text("WERRORS")').click()
    detail = page.locator("#detail")
    reject = detail.locator('[data-action="reject"]')
    reject.click()
    error = detail.locator(".review-decision .form-error")
    expect(error).to_have_text("A rejection needs feedback: the participant is shown why.")
    feedback = page.get_by_label("Feedback to the worker (needed to reject)")
    expect(feedback).to_have_attribute("aria-invalid", "true")
    expect(feedback).to_have_attribute("aria-describedby", str(error.get_attribute("id")))
    expect(detail.locator(".bonus .form-error")).to_be_hidden()
    # Under Reject, above the bonuses (not under "Pay the bonus").
    error_box, reject_box = error.bounding_box(), reject.bounding_box()
    pay_box = detail.locator('[data-action="bonus"]').bounding_box()
    assert error_box and reject_box and pay_box
    assert reject_box["y"] < error_box["y"] < pay_box["y"]
    # The bonus form's own error is by its button (a reason of spaces is none).
    page.get_by_label("Bonus (USD)").fill("1.00")
    page.get_by_label("Reason, shown to the participant").fill("   ")
    detail.locator('[data-action="bonus"]').click()
    bonus_error = detail.locator(".bonus .form-error")
    expect(bonus_error).to_have_text("A bonus needs an amount and a reason.")
    # Both boxes measured now: boxes are relative to the viewport, and the click may have
    # scrolled the page since the button was measured above.
    bonus_box = bonus_error.bounding_box()
    pay_box = detail.locator('[data-action="bonus"]').bounding_box()
    assert bonus_box and pay_box and bonus_box["y"] > pay_box["y"]


def test_times_are_written_one_way_with_their_zone(browser: Browser, server: LiveServer) -> None:
    """In a browser whose clock is in New York, the replica and the dashboard both write UTC
    times as "2026-11-26 10:42:07 UTC", and the same instant the same way."""
    context = browser.new_context(timezone_id="America/New_York")
    try:
        page = context.new_page()
        submit_a_hit(page, server, "WTIMES")
        (submitted,) = server.query(
            "SELECT submitted_at FROM mturk_replica_submissions WHERE worker_id = 'WTIMES'"
        )
        page.goto(f"{server.url}/mturk")
        row = page.locator('#assignments tr[data-worker="WTIMES"]')
        accepted, returned, sent = (row.locator("td").nth(k).inner_text() for k in (3, 4, 5))
        assert TIME.match(accepted) and TIME.match(sent), (accepted, sent)
        assert returned == ""
        replica_sent = (
            page.locator('#submissions tr:has-text("WTIMES") td').first.inner_text().strip()
        )
        assert TIME.match(replica_sent), replica_sent
        page.goto(f"{server.url}/dashboard")
        expect(page.locator("#refreshed")).to_have_text(re.compile(r"^updated .* UTC$"))
        dashboard_sent = page.locator(
            '#mturk-submissions tr:has-text("WTIMES") td'
        ).first.inner_text()
        assert dashboard_sent == replica_sent
        assert str(submitted[0]).replace("T", " ")[:19] in dashboard_sent
        page.locator('#participants tr[data-participant]:has-text("WTIMES")').click()
        history = page.locator("#detail .history li")
        expect(history.first).to_be_visible()
        for text in history.all_inner_texts():
            stamp = re.search(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d UTC", text)
            assert stamp is not None, text
    finally:
        context.close()


def test_the_summary_counts_statuses_and_domains_in_separate_rows(
    page: Page, server: LiveServer
) -> None:
    submit_a_hit(page, server, "WSUMMARY")
    page.goto(f"{server.url}/dashboard")
    statuses = page.locator('#summary [data-group="status"]')
    domains = page.locator('#summary [data-group="domain"]')
    expect(statuses).to_have_accessible_name("By status")
    expect(domains).to_have_accessible_name("By domain")
    expect(statuses.locator('[data-name="submitted"]')).to_be_visible()
    expect(domains.locator('[data-name="navigation"]')).to_be_visible()
    assert statuses.locator('[data-name="navigation"]').count() == 0
    assert domains.locator('[data-name="submitted"]').count() == 0
    rows = page.locator("#participants tr[data-participant]").count()
    counted = sum(
        int(text.rsplit(": ", 1)[1]) for text in statuses.locator(".badge").all_inner_texts()
    )
    assert counted == rows


def test_the_review_shows_the_ground_the_quality_checks_suggest(
    page: Page, server: LiveServer
) -> None:
    submit_a_hit(page, server, "WSUGGEST")
    (participant,) = server.query(
        "SELECT id FROM participants WHERE platform_participant_id = 'WSUGGEST'"
    )
    page.goto(f"{server.url}/dashboard")
    page.locator(f'#participants tr[data-participant="{participant.id}"]').click()
    detail = page.locator("#detail")
    suggestion = detail.locator('[data-testid="suggested-ground"]')
    expect(suggestion).to_have_text(
        "Suggested ground: none (the quality checks support no rejection).", timeout=WAIT_MS
    )
    expect(detail.locator('[data-quality="attention-checks"]')).to_have_text(
        "Attention checks: none taken"
    )
    # A failed attention check, in a study of under five minutes: Prolific's FAILED_CHECK.
    server.query(
        "INSERT INTO attention_checks (participant_id, number, after_ordinal, size, start_cell,"
        " star_cell, moves_allowed, status, cell, moves) VALUES (:id, 0, 0, 5, 20, 4, 8,"
        " 'failed', 20, :moves)",
        id=participant.id,
        moves='["LEFT", "LEFT", "LEFT", "LEFT", "LEFT", "LEFT", "LEFT", "LEFT"]',
    )
    page.reload()
    page.locator(f'#participants tr[data-participant="{participant.id}"]').click()
    expect(suggestion).to_have_text(
        "Suggested ground: FAILED_CHECK (1 of 1 attention checks failed).", timeout=WAIT_MS
    )
    expect(detail.locator('[data-quality="attention-checks"]')).to_have_text(
        "Attention checks failed: 1 of 1"
    )


def test_reject_asks_first_and_the_opened_participant_is_scrolled_to_and_focused(
    page: Page, server: LiveServer
) -> None:
    """Reject, like Approve and Pay, asks before it sends (dismissed: nothing is sent). Opening
    a participant, by mouse or by keyboard, brings their detail panel (below the table, out of
    sight in a 1024 x 640 window) into view and puts the focus on its heading."""
    page.set_viewport_size({"width": 1024, "height": 640})
    submit_a_hit(page, server, "WREJECT")
    page.goto(f"{server.url}/dashboard")
    row = page.locator('#participants tr[data-participant]:has-text("WREJECT")')
    heading = page.locator("#detail h2")
    expect(row).to_be_visible()
    page.evaluate("() => window.scrollTo(0, 0)")
    row.click()
    expect(heading).to_be_focused()
    expect(heading).to_be_in_viewport()
    page.wait_for_function(
        "() => Math.abs(document.querySelector('#detail').getBoundingClientRect().top) < 2"
    )

    detail = page.locator("#detail")
    feedback = "The submission is empty: no task was taught, so it cannot be approved, sorry."
    page.get_by_label("Feedback to the worker (needed to reject)").fill(feedback)
    asked: list[str] = []
    page.once("dialog", lambda dialog: (asked.append(dialog.message), dialog.dismiss()))
    detail.locator('[data-action="reject"]').click()
    expect(detail.locator('[data-action="reject"]')).to_be_enabled()
    reviews = (
        "SELECT r.decision FROM reviews r JOIN participants p "
        "ON p.id = r.participant_id WHERE p.platform_participant_id = 'WREJECT'"
    )
    assert server.query(reviews) == []
    assert asked == [
        "Reject this submission? A decision is final: the participant is not paid for it."
    ]
    page.once("dialog", lambda dialog: (asked.append(dialog.message), dialog.accept()))
    detail.locator('[data-action="reject"]').click()
    expect(detail.locator('[data-review="rejected"]')).to_contain_text(feedback)
    assert len(asked) == 2
    assert [tuple(r) for r in server.query(reviews)] == [("rejected",)]

    # By keyboard: the row, Enter, and the focus is on the panel's heading, in view.
    page.evaluate("() => window.scrollTo(0, 0)")
    row.focus()
    page.keyboard.press("Enter")
    expect(heading).to_be_focused()
    expect(heading).to_be_in_viewport()
