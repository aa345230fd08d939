"""Prolific's study events: ``study.status.change`` gives the server the study's Prolific status
and when it took it (each event applied once, an older one never over a newer one), and
``study.has_high_return_rate`` a warning the admin API shows beside our own count of returns."""

from __future__ import annotations

import time
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from server.app.main import create_app
from server.app.platforms import prolific_sync
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import ProlificEvent, ProlificStudy
from server.app.study_file import StudyConfig
from tests.app.platforms.test_prolific import ADMIN, draft

# The server with BAM_PROLIFIC_WEBHOOK_SECRET set, and a study that finishes on Prolific.
from tests.app.platforms.test_prolific_sync import client as client
from tests.app.platforms.test_prolific_sync import send, teaching
from tests.app.platforms.test_prolific_sync import settings as settings
from tests.app.platforms.test_prolific_sync import study as study
from tests.support.server import ADMIN_TOKEN, live

STUDY = "a" * 24


def study_status(status: str, study_id: str = STUDY) -> dict[str, Any]:
    """Prolific's ``study.status.change`` body (docs: webhooks, receiving)."""
    return {
        "resource_id": study_id,
        "event_type": "study.status.change",
        "metadata": {},
        "status": status,
    }


def high_return_rate(metadata: dict[str, Any] | None = None) -> dict[str, Any]:
    return {
        "resource_id": STUDY,
        "event_type": "study.has_high_return_rate",
        "metadata": metadata or {},
    }


def stored(db: Database, study_id: str = STUDY) -> ProlificStudy | None:
    with db.read() as s:
        return s.get(ProlificStudy, study_id)


def studies(client: httpx.Client) -> dict[str, dict[str, Any]]:
    answer = client.get("/api/admin/prolific-studies", headers=ADMIN)
    assert answer.status_code == 200, answer.text
    return {view["study_id"]: view for view in answer.json()}


def test_the_studys_status_is_kept_once_and_in_the_order_the_events_happened(
    client: TestClient, db: Database
) -> None:
    published = send(client, study_status("ACTIVE"), "st-1", happened="1700000000")
    assert published.status_code == 200 and published.json()["result"] == "applied"
    row = stored(db)
    assert row is not None and row.status == "ACTIVE"
    assert row.status_at is not None and row.status_at.timestamp() == 1700000000
    # Redelivered (the same X-Event-ID): answered, applied once.
    again = send(client, study_status("ACTIVE"), "st-1", happened="1700000000")
    assert again.status_code == 200 and again.json()["result"] == "already applied"
    # The study filled (later), and the pause (earlier) arrives after it: it leaves the status.
    full = send(client, study_status("AWAITING REVIEW"), "st-3", happened="1700000300")
    assert full.json()["result"] == "applied"
    late = send(client, study_status("PAUSED"), "st-2", happened="2023-11-14T22:15:00Z")
    assert late.status_code == 200 and "older" in late.json()["result"]
    row = stored(db)
    assert row is not None and row.status == "AWAITING REVIEW"
    assert row.status_at is not None and row.status_at.timestamp() == 1700000300
    with db.read() as s:
        assert s.scalar(select(func.count()).select_from(ProlificEvent)) == 3
    view = studies(client)[STUDY]
    assert view["status"] == "AWAITING REVIEW" and view["high_return_rate"] is None


def test_a_study_status_prolific_does_not_have_is_refused_and_nothing_is_recorded(
    client: TestClient, db: Database
) -> None:
    refused = send(client, study_status("FINISHED"), "st-1")
    assert refused.status_code == 400 and "FINISHED" in refused.json()["detail"]
    assert stored(db) is None
    with db.read() as s:
        assert s.scalar(select(func.count()).select_from(ProlificEvent)) == 0
    # Without a study id, nothing to apply: answered and left.
    empty = send(client, {**study_status("ACTIVE"), "resource_id": ""}, "st-2")
    assert empty.status_code == 200 and empty.json()["result"] == "no resource_id"


def test_a_study_event_whose_effect_failed_is_applied_when_redelivered(
    db: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    def crash(*args: Any) -> str:
        raise RuntimeError("the server stopped")

    with monkeypatch.context() as patched:
        patched.setattr(prolific_sync, "_apply_study_status", crash)
        with pytest.raises(RuntimeError):
            prolific_sync.apply_webhook(db, "st-1", study_status("PAUSED"))
    assert prolific_sync.apply_webhook(db, "st-1", study_status("PAUSED")) == "applied"
    row = stored(db)
    assert row is not None and row.status == "PAUSED"


def test_a_high_return_rate_is_shown_with_our_share_of_returns_and_their_reasons(
    client: TestClient, db: Database
) -> None:
    # Four participants of the study: one returned on Prolific, one timed out, one declined
    # consent and then returned, one still teaching.
    teaching(db, "b" * 24, "c" * 24)
    teaching(db, "d" * 24, "e" * 24)
    teaching(db, "f" * 24, "1" * 24, status="declined")
    teaching(db, "2" * 24, "3" * 24)
    for submission, status in (("c", "RETURNED"), ("e", "TIMED-OUT"), ("1", "RETURNED")):
        event = {
            "event_type": "submission.status.change",
            "resource_id": submission * 24,
            "status": status,
        }
        assert send(client, event, f"sub-{submission}").json()["result"] == "applied"
    assert studies(client)[STUDY]["high_return_rate"] is None
    warned = send(client, high_return_rate({"rate": 0.5}), "hr-1", happened="1700000000")
    assert warned.status_code == 200 and warned.json()["result"] == "applied"
    again = send(client, high_return_rate({"rate": 0.5}), "hr-1", happened="1700000000")
    assert again.json()["result"] == "already applied"
    warning = studies(client)[STUDY]["high_return_rate"]
    assert warning is not None
    assert warning["metadata"] == {"rate": 0.5}
    assert (warning["arrived"], warning["returned"], warning["share_returned"]) == (4, 3, 0.75)
    assert warning["reasons"] == {
        "returned on Prolific": 2,
        "timed out": 1,
        "had declined consent": 1,
    }
    # The warning does not touch the study's status.
    assert studies(client)[STUDY]["status"] is None


def test_the_replica_sends_signed_study_status_changes_that_the_server_keeps(
    db: Database, settings: Settings, study: StudyConfig, executor: ProcessPoolExecutor
) -> None:
    """Published, paused, started, filled by its one place, stopped: each change reaches the
    server as a signed ``study.status.change``, the last one kept."""
    app = create_app(settings, study, db=db, executor=executor)
    token = {"Authorization": f"Token {ADMIN_TOKEN}"}

    def seen() -> list[str]:
        with db.read() as s:
            events = s.scalar(
                select(func.count())
                .select_from(ProlificEvent)
                .where(ProlificEvent.event_type == "study.status.change")
            )
            row = s.get(ProlificStudy, created["id"])
            return [str(events), row.status if row else ""]

    def wait_for(events: int, status: str) -> None:
        deadline = time.monotonic() + 60
        while seen() != [str(events), status]:
            assert time.monotonic() < deadline, seen()
            time.sleep(0.05)

    with live(app) as base, httpx.Client(base_url=base, headers=ADMIN) as browser:
        made = draft(1)
        made["external_study_url"] = (
            f"{base}/study?PROLIFIC_PID={{{{%PROLIFIC_PID%}}}}&STUDY_ID={{{{%STUDY_ID%}}}}"
            "&SESSION_ID={{%SESSION_ID%}}"
        )
        created = browser.post("/prolific/api/v1/studies/", json=made, headers=token).json()
        assert seen() == ["0", ""]  # a draft sends nothing
        path = f"/prolific/api/v1/studies/{created['id']}/transition/"
        for events, (action, status) in enumerate(
            (("PUBLISH", "ACTIVE"), ("PAUSE", "PAUSED"), ("START", "ACTIVE")), start=1
        ):
            moved = browser.post(path, json={"action": action}, headers=token)
            assert moved.status_code == 200 and moved.json()["status"] == status, moved.text
            wait_for(events, status)
        # A refused transition changes nothing and sends nothing.
        refused = browser.post(path, json={"action": "PUBLISH"}, headers=token)
        assert refused.status_code == 400
        # The one place taken: AWAITING REVIEW.
        entered = browser.post(f"/prolific/studies/{created['id']}/take-part")
        assert entered.status_code == 303, entered.text
        wait_for(4, "AWAITING REVIEW")
        stopped = browser.post(path, json={"action": "STOP"}, headers=token)
        assert stopped.json()["status"] == "COMPLETED"
        wait_for(5, "COMPLETED")
        assert studies(browser)[created["id"]]["status"] == "COMPLETED"
