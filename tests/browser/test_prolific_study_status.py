"""The dashboard's line on the Prolific study: its status from Prolific's study.status.change
webhook, and the study.has_high_return_rate warning with our share of returns."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
from playwright.sync_api import Page, expect

from server.app.platforms.prolific_sync import signature
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

pytestmark = pytest.mark.browser

TOKEN = {"Authorization": f"Token {ADMIN_TOKEN}"}
ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
SECRET = "c3R1ZHktZXZlbnRzLXNlY3JldA=="


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    config = study_toml(
        mode="prolific", domains_toml=domain_toml("navigation", "wall"), learners='["cloning"]'
    ).replace('mode = "prolific"', 'mode = "prolific"\nprolific_code = "C1A2B3C4"')
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("BAM_PROLIFIC_WEBHOOK_SECRET", SECRET)
        yield from run_live_server(tmp_path_factory.mktemp("prolific-study-status"), config)


def deliver(http: httpx.Client, payload: dict[str, Any], event_id: str) -> None:
    """Prolific's signed delivery of one event."""
    body = json.dumps(payload).encode()
    stamp = str(int(time.time()))
    answer = http.post(
        "/prolific/webhook",
        content=body,
        headers={
            "Content-Type": "application/json",
            "X-Prolific-Request-Signature": signature(SECRET, stamp, body),
            "X-Prolific-Request-Timestamp": stamp,
            "X-Event-ID": event_id,
        },
    )
    assert answer.status_code == 200, answer.text


def test_the_dashboard_shows_the_studys_status_and_a_high_return_rate(
    page: Page, server: LiveServer
) -> None:
    with httpx.Client(base_url=server.url, headers=ADMIN, timeout=60) as http:
        made = draft(3)
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
        # Two participants arrive; one returns the study on Prolific.
        submissions = []
        for _ in range(2):
            http.cookies.clear()
            sent = http.post(f"/prolific/studies/{study}/take-part")
            link = dict(httpx.URL(sent.headers["location"]).params)
            assert http.post("/api/arrivals", json=link).status_code == 201
            submissions.append(link["SESSION_ID"])
        deliver(
            http,
            {
                "resource_id": submissions[0],
                "event_type": "submission.status.change",
                "status": "RETURNED",
            },
            "ev-returned",
        )
        deliver(
            http,
            {
                "resource_id": study,
                "event_type": "study.status.change",
                "metadata": {},
                "status": "PAUSED",
            },
            "ev-paused",
        )
        deliver(
            http,
            {"resource_id": study, "event_type": "study.has_high_return_rate", "metadata": {}},
            "ev-high-return-rate",
        )
    watch = Watch(server.url).attach(page)
    admin_login(page, server, "/dashboard")
    line = page.locator(f'#prolific-studies [data-prolific-study="{study}"]')
    expect(line.locator('[data-study-status="PAUSED"]')).to_have_text("PAUSED")
    warning = line.locator(f'[data-high-return-rate="{study}"]')
    expect(warning).to_be_visible()
    expect(warning).to_contain_text("high return rate")
    expect(warning).to_contain_text("Returned so far: 1 of 2 (50 %)")
    expect(warning).to_contain_text("returned on Prolific: 1")
    # The line is above the participants' table.
    top = page.locator("#prolific-studies").bounding_box()
    table = page.locator("#participants").bounding_box()
    assert top is not None and table is not None and top["y"] < table["y"]
    assert axe_violations(page) == []
    # A change on Prolific while the page is open shows at its next refresh.
    with httpx.Client(base_url=server.url, timeout=60) as http:
        deliver(
            http,
            {
                "resource_id": study,
                "event_type": "study.status.change",
                "metadata": {},
                "status": "ACTIVE",
            },
            "ev-started",
        )
    expect(line.locator('[data-study-status="ACTIVE"]')).to_have_text("ACTIVE", timeout=15000)
    expect(warning).to_be_visible()
    watch.check()


def test_the_dashboard_lists_the_servers_own_changes_to_the_study(
    page: Page, server: LiveServer
) -> None:
    """Each change the server made to its Prolific study by itself (the concurrency held to its
    capacity, a pause under load) is listed under the study's line, newest first."""
    study = "f" * 24
    server.query(
        "INSERT INTO prolific_studies (study_id, status) VALUES (:study, 'PAUSED')", study=study
    )
    for at, change, value, reason, outcome in (
        ("2026-01-05 09:00:00+00", "max_concurrent_submissions", 3, "the server admits 3", "done"),
        ("2026-01-05 09:10:00+00", "PAUSE", None, "the update queue makes agents wait", "done"),
    ):
        server.query(
            "INSERT INTO prolific_study_changes (study_id, at, change, value, reason, outcome) "
            "VALUES (:study, :at, :change, :value, :reason, :outcome)",
            study=study,
            at=at,
            change=change,
            value=value,
            reason=reason,
            outcome=outcome,
        )
    watch = Watch(server.url).attach(page)
    admin_login(page, server, "/dashboard")
    listed = page.locator(f'#prolific-studies [data-prolific-changes="{study}"] li')
    expect(listed).to_have_count(2)
    expect(listed.nth(0)).to_contain_text("paused (the update queue makes agents wait)")
    expect(listed.nth(1)).to_contain_text("concurrency set to 3 (the server admits 3)")
    assert axe_violations(page) == []
    watch.check()
