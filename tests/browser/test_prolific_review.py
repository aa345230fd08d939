"""The dashboard and a Prolific decliner who never returns: their NO_CONSENT code completed the
submission on the replica, so the dashboard flags them as asked to return and not returned,
shows the day Prolific would approve and pay the submission by itself, warns in the last week,
and approves them through the replica like anyone else."""

from __future__ import annotations

import re
from collections.abc import Iterator

import httpx
import pytest
from playwright.sync_api import Page, expect

from tests.app.platforms.test_prolific import draft
from tests.browser.conftest import (
    ADMIN_TOKEN,
    LiveServer,
    Watch,
    admin_login,
    axe_violations,
    domain_toml,
    run_live_server,
    study_toml,
)
from tests.support.server import Participant

pytestmark = pytest.mark.browser

TOKEN = {"Authorization": f"Token {ADMIN_TOKEN}"}
ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    config = study_toml(
        mode="prolific", domains_toml=domain_toml("navigation", "wall"), learners='["cloning"]'
    ).replace(
        'mode = "prolific"',
        'mode = "prolific"\nprolific_code = "C1A2B3C4"\nprolific_no_consent_code = "NOCONSNT"',
    )
    yield from run_live_server(tmp_path_factory.mktemp("prolific-review"), config)


def a_decliner(server: LiveServer) -> tuple[int, str]:
    """A participant of a replica study who declines consent and goes back with NO_CONSENT;
    the server then polls the study (this server has no webhook secret). Their id and
    submission."""
    with httpx.Client(base_url=server.url, headers=ADMIN, timeout=60) as http:
        made = draft(2)
        made["external_study_url"] = (
            f"{server.url}/study?PROLIFIC_PID={{{{%PROLIFIC_PID%}}}}&STUDY_ID={{{{%STUDY_ID%}}}}"
            "&SESSION_ID={{%SESSION_ID%}}"
        )
        study = http.post("/prolific/api/v1/studies/", json=made, headers=TOKEN).json()["id"]
        http.post(
            f"/prolific/api/v1/studies/{study}/transition/",
            json={"action": "PUBLISH"},
            headers=TOKEN,
        )
        sent = http.post(f"/prolific/studies/{study}/take-part")
        link = dict(httpx.URL(sent.headers["location"]).params)
        person = Participant(http, http.post("/api/arrivals", json=link).json()["token"])
        declined = person.act("/api/participant/consent", agree=False)["participant"]
        landed = http.get(declined["completion"]["redirect_url"])
        assert landed.status_code == 200 and "AWAITING REVIEW" in landed.text
        polled = http.post("/api/admin/reconciliation", params={"prolific_study": study})
        assert polled.json()["prolific_statuses"] == {link["SESSION_ID"]: "AWAITING REVIEW"}
        return int(person.get("/api/participant")["participant_id"]), link["SESSION_ID"]


def test_a_decliner_is_flagged_warned_about_and_approved(page: Page, server: LiveServer) -> None:
    participant, submission = a_decliner(server)
    watch = Watch(server.url).attach(page)
    admin_login(page, server, "/dashboard")
    row = page.locator(f'#participants tr[data-participant="{participant}"]')
    expect(row.locator('[data-prolific-status="AWAITING REVIEW"]')).to_have_count(1)
    expect(row.locator(".return-requested")).to_have_text("asked to return; not returned yet")
    due = row.locator("[data-auto-approval]")
    expect(due).to_have_attribute("data-soon", "false")
    expect(due).to_have_text(re.compile(r"^auto-approved \d{4}-\d\d-\d\d \d\d:\d\d:\d\d UTC$"))

    # Completed 15 days ago: six days left, inside the week's warning.
    server.query(
        "UPDATE participants SET platform_completed_at = datetime('now', '-15 days') "
        "WHERE id = :id",
        id=participant,
    )
    page.reload()
    row = page.locator(f'#participants tr[data-participant="{participant}"]')
    expect(row.locator('[data-auto-approval][data-soon="true"]')).to_contain_text("⚠")
    row.click()
    detail = page.locator("#detail")
    expect(detail.locator(".auto-approval.soon")).to_contain_text("in less than a week")
    expect(detail.locator("[data-return-requested]")).to_contain_text(
        "Asked to return; not returned yet"
    )
    expect(detail).to_contain_text("They declined consent")
    expect(detail.locator("form.bonus")).to_have_count(0)  # bonuses are for submitted work
    assert axe_violations(page) == []  # the flags and the warning as readable as the rest
    page.on("dialog", lambda dialog: dialog.accept())
    detail.locator('[data-action="approve"]').click()
    expect(detail.locator('[data-review="approved"]')).to_have_count(1)
    row = page.locator(f'#participants tr[data-participant="{participant}"]')
    expect(row.locator('[data-prolific-status="APPROVED"]')).to_have_count(1)
    expect(row.locator("[data-auto-approval]")).to_have_count(0)
    (replica,) = server.query(
        "SELECT status FROM prolific_replica_submissions WHERE id = :id", id=submission
    )
    assert replica.status == "APPROVED"
    watch.check()
