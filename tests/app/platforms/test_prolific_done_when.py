"""The whole Prolific study from our side, over real HTTP, as Prolific behaves, with no webhook
setting: made and published, its concurrency set to the server's capacity by the server; a
decliner who never returns, flagged before Prolific's auto-approval; a participant who
finished but timed out, reviewed, approved and paid, the pay answering 429 after paying and
settled without a second payment; the study full, a return that waits for ``start``; the
server pausing the study under load and starting it once the queue drained; a message to one
participant; and the export agreeing with the replica on every count."""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from datetime import timedelta
from typing import Any

import httpx
import pytest
from sqlalchemy import select

from server.app.export.tables import export_tables
from server.app.main import create_app
from server.app.platforms.prolific import ProlificBackend, ProlificClient, draft_study
from server.app.platforms.prolific_replica import ReplicaTransport
from server.app.routers.prolific import follow_capacity
from server.app.storage.db import Database
from server.app.storage.models import Participant as ParticipantRow
from server.app.storage.models import utcnow
from server.app.storage.replica_models import ProlificReplicaMessage, ProlificReplicaPayment
from server.app.study_file import StudyConfig
from server.app.updates.queue import QueueState
from server.commands.main import main
from tests.app.platforms.test_prolific import FailingPay
from tests.app.platforms.test_prolific_rehearsal import Person, prolific_study
from tests.support.server import (
    ADMIN_TOKEN,
    demonstrate_each_task,
    live,
    make_settings,
    wait_until,
)

ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
CALM = QueueState(0, 0, 0, 0.0, 1, 0, 0)
LOADED = QueueState(3, 1, 3, 12.0, 1, 0, 0)  # three participants wait 12 s for their agents


@pytest.fixture
def study() -> StudyConfig:
    return prolific_study(
        max_active_participants=4,
        prolific={
            "name": "Teaching robots",
            "description": "Teach simulated robots in a grid world with the arrow keys.",
            "places": 3,
            "reward": 6.0,
            "estimated_minutes": 30,
            "maximum_minutes": 90,
            "public_url": "https://study.example.org",
        },
    )


@pytest.fixture
def server(
    db: Database, study: StudyConfig, executor: ProcessPoolExecutor
) -> Iterator[tuple[str, Any]]:
    settings = make_settings(db.engine.url.render_as_string(hide_password=False))
    assert settings.prolific_webhook_secret is None  # nothing to remember
    app = create_app(settings, study, db=db, executor=executor)
    with live(app) as base:
        yield base, app


def command(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    status = main(argv)
    out, err = capsys.readouterr()
    assert status == 0, err
    return out


def ours(db: Database) -> dict[int, tuple[str, str | None]]:
    with db.read() as s:
        return {p.id: (p.status, p.platform_status) for p in s.scalars(select(ParticipantRow))}


def listed(base: str, participant: int) -> dict[str, Any]:
    rows = httpx.get(f"{base}/api/admin/participants", headers=ADMIN).json()
    return next(row for row in rows if row["participant_id"] == participant)


def study_status(base: str, study_id: str) -> str | None:
    views = httpx.get(f"{base}/api/admin/prolific-studies", headers=ADMIN).json()
    return next((v["status"] for v in views if v["study_id"] == study_id), None)


@pytest.mark.slow
def test_a_prolific_study_from_create_to_export_as_prolific_behaves(
    server: tuple[str, Any],
    db: Database,
    study: StudyConfig,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    base, app = server
    state = app.state.server
    monkeypatch.setenv("BAM_ADMIN_TOKEN", ADMIN_TOKEN)
    monkeypatch.setenv("BAM_DATABASE_URL", db.engine.url.render_as_string(hide_password=False))
    monkeypatch.delenv("BAM_PROLIFIC_WEBHOOK_SECRET", raising=False)
    replica = ["--replica", base]
    client = ProlificClient(f"{base}/prolific/api/v1", ADMIN_TOKEN, first_wait=0.01)

    # Made (as `create` makes it, with more at once than the server admits) and published.
    study_id = client.create_study(draft_study(study, 6, base))["id"]
    out = command(["prolific", "publish", study_id, *replica], capsys)
    assert out.strip().endswith(f"study {study_id}: ACTIVE")
    wait_until(lambda: study_status(base, study_id) == "ACTIVE", "the study's status event")
    # The server holds Prolific's concurrency to what it admits.
    follow_capacity(state, CALM)
    assert client.get_study(study_id)["submissions_config"]["max_concurrent_submissions"] == 4

    # A decliner: the NO_CONSENT code completes the submission; they never return it.
    decliner = Person(base, study_id)
    declined = decliner.consent(agree=False)
    decliner.leave(declined["completion"])
    wait_until(
        lambda: ours(db)[decliner.id] == ("declined", "AWAITING REVIEW"), "the decliner's code"
    )
    # Two weeks on, the dashboard flags them, before Prolific approves and pays them.
    with db.write() as s:
        row = s.get(ParticipantRow, decliner.id)
        assert row is not None and row.platform_completed_at is not None
        row.platform_completed_at -= timedelta(days=15)
    flagged = listed(base, decliner.id)
    assert flagged["return_requested_at"] is not None and flagged["awaits_decision"]
    assert flagged["auto_approval_soon"]
    assert utcnow() < _time(flagged["auto_approval_at"]) < utcnow() + timedelta(days=7)

    # One finishes teaching, and their submission times out before their code reaches
    # Prolific: kept as they were, reviewable, approved and paid a bonus.
    late = Person(base, study_id)
    late.consent()
    session = late.api.act("/api/participant/start")["participant"]["current_session_id"]
    demonstrate_each_task(late.api, session)
    assert late.api.act(f"/api/sessions/{session}/finish")["participant"]["status"] == "completed"
    late.end("time-out")
    wait_until(lambda: ours(db)[late.id] == ("completed", "TIMED-OUT"), "the time-out")
    assert listed(base, late.id)["awaits_decision"]
    approved = httpx.post(
        f"{base}/api/admin/participants/{late.id}/approval", json={}, headers=ADMIN
    )
    assert approved.status_code == 200, approved.text
    # Approved, the timed-out finisher is paid their reward, as Prolific lets a researcher do.
    wait_until(lambda: ours(db)[late.id][1] == "APPROVED", "the approval of the timed-out")

    # Two more fill the study (the decliner holds a place; the timed-out one gave theirs back).
    first = Person(base, study_id)
    first.consent()
    first.teach_and_submit()
    leaver = Person(base, study_id)
    leaver.consent()
    assert client.get_study(study_id)["status"] == "AWAITING REVIEW"
    wait_until(lambda: study_status(base, study_id) == "AWAITING REVIEW", "the full study")
    # One returns: the place is free, but a full study stays full until `start`.
    leaver.end("return")
    wait_until(lambda: ours(db)[leaver.id] == ("returned", "RETURNED"), "the return")
    with httpx.Client(base_url=base, headers=ADMIN) as browser:
        refused = browser.post(f"/prolific/studies/{study_id}/take-part")
    assert refused.status_code == 409 and "AWAITING REVIEW" in refused.text
    out = command(["prolific", "start", study_id, *replica], capsys)
    assert out.strip() == f"study {study_id}: ACTIVE"
    wait_until(lambda: study_status(base, study_id) == "ACTIVE", "the start's status event")

    # Under load the server pauses the study by itself, and starts it once the queue drained.
    reading = follow_capacity(state, LOADED, follow_capacity(state, CALM))
    assert client.get_study(study_id)["status"] == "ACTIVE"  # one reading of the wait: not yet
    follow_capacity(state, LOADED, reading)
    assert client.get_study(study_id)["status"] == "PAUSED"
    wait_until(lambda: study_status(base, study_id) == "PAUSED", "the pause's status event")
    follow_capacity(state, CALM)
    assert client.get_study(study_id)["status"] == "ACTIVE"
    [view] = [
        v
        for v in httpx.get(f"{base}/api/admin/prolific-studies", headers=ADMIN).json()
        if v["study_id"] == study_id
    ]
    assert [c["change"] for c in view["changes"]] == [
        "START",
        "PAUSE",
        "max_concurrent_submissions",
    ]
    last = Person(base, study_id)
    last.consent()
    last.teach_and_submit()

    # The two who submitted are approved; one is sent a message.
    bulk = httpx.post(
        f"{base}/api/admin/approvals",
        json={"participant_ids": [first.id, last.id]},
        headers=ADMIN,
        timeout=120,
    )
    assert sorted(bulk.json()["approved"]) == sorted([first.id, last.id])
    # Its bonus's pay answers 429 after paying: in doubt, settled from bonus_payments.
    backend = state.review_backend("prolific")
    state.reviews["prolific"] = ProlificBackend(
        ProlificClient(
            "http://replica/prolific/api/v1",
            ADMIN_TOKEN,
            transport=FailingPay(ReplicaTransport(db, ADMIN_TOKEN), "paid-429"),
        ),
        "GBP",
        name="prolific-replica",
    )
    bonus = {"amount": "0.80", "reason": "Taught all six tasks", "unique_token": "first-bonus"}
    doubt = httpx.post(
        f"{base}/api/admin/participants/{first.id}/bonuses", json=bonus, headers=ADMIN
    )
    assert doubt.status_code == 502 and "is in doubt" in doubt.text
    state.reviews["prolific"] = backend
    settled = httpx.post(
        f"{base}/api/admin/participants/{first.id}/bonuses", json=bonus, headers=ADMIN
    )
    assert [b["state"] for b in settled.json()["bonuses"]] == ["paid"]

    out = command(
        [
            "prolific",
            "message",
            "--study",
            study_id,
            "--to",
            first.link["PROLIFIC_PID"],
            "--body",
            "Thank you: your bonus follows.",
            *replica,
        ],
        capsys,
    )
    assert "sent to 1 participant(s)" in out

    # The export agrees with the replica on every count.
    counted = client.submission_counts(study_id)
    total = counted.pop("TOTAL")
    assert {k: v for k, v in counted.items() if v} == {
        "AWAITING REVIEW": 1,  # the decliner
        "APPROVED": 3,
        "RETURNED": 1,
    }
    tables = export_tables(db)
    participants = tables["participants"]
    assert len(participants) == total
    assert Counter(participants["prolific_status"]) == {k: v for k, v in counted.items() if v}
    assert Counter(tables["reviews"]["decision"]) == {"approved": 3}
    with db.read() as s:
        paid = s.scalars(select(ProlificReplicaPayment.amount)).all()
        sent = s.scalars(select(ProlificReplicaMessage.recipient_id)).all()
    assert list(paid) == [80]  # paid once
    bonuses = tables["bonuses"]
    assert list(bonuses["amount"].astype(str)) == ["0.80"]
    assert set(bonuses["payment_state"]) == {"paid"}
    assert list(tables["messages"]["study_id"]) == [study_id] and len(sent) == 1
    client.close()


def _time(text: str) -> Any:
    from datetime import datetime

    return datetime.fromisoformat(text)
