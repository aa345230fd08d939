"""The Prolific replica's webhooks (the workspace's secret, subscriptions confirmed with their
X-Hook-Secret, their deliveries), its participant groups (made, joined by a completion code's
action, blocking or allowing a study's participants), its scheduled publishing and the PATCH
of a published study's concurrency; its webhooks reach the server with no setting; its API's
token is guessed no faster than the dashboard's sign-in; a pay that Prolific accepted (202)
is not taken as paid."""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from datetime import UTC, datetime, timedelta
from decimal import Decimal
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from server.app.main import create_app
from server.app.platforms import review
from server.app.platforms.prolific import ProlificBackend, ProlificClient, ProlificRefused
from server.app.platforms.prolific_replica import WORKSPACE_ID, ReplicaTransport, hook_secret
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import Bonus, Participant
from server.app.storage.replica_models import ProlificReplicaStudy
from server.app.study_file import StudyConfig
from tests.app.platforms.test_prolific import (
    ADMIN,
    age,
    draft,
    payments,
    prolific_participant,
    state_of,
)
from tests.support.server import ADMIN_TOKEN, live, study_config, wait_until

TOKEN = {"Authorization": f"Token {ADMIN_TOKEN}"}


def replica_client(db: Database, transport: httpx.BaseTransport | None = None) -> ProlificClient:
    return ProlificClient(
        "http://replica/prolific/api/v1",
        ADMIN_TOKEN,
        transport=transport or ReplicaTransport(db, ADMIN_TOKEN),
        first_wait=0.0,
    )


def published(client: ProlificClient, fields: dict[str, Any] | None = None) -> str:
    study = client.create_study(fields or draft())
    client.transition_study(study["id"], "PUBLISH")
    return str(study["id"])


# -- webhooks -----------------------------------------------------------------------------------
def test_the_replica_makes_a_secret_subscribes_confirms_and_lists_as_prolific(
    db: Database,
) -> None:
    client = replica_client(db)
    # No subscription before the workspace has a secret, as on Prolific.
    with pytest.raises(ProlificRefused, match="Create a secret for your workspace"):
        client.subscribe(WORKSPACE_ID, "study.status.change", "https://study.example.org/hook")
    first = client.create_hook_secret(WORKSPACE_ID)
    second = client.create_hook_secret(WORKSPACE_ID)  # a new one replaces the old
    assert first != second
    listed = client.request("GET", "hooks/secrets/", params={"workspace_id": WORKSPACE_ID})
    assert [s["value"] for s in listed["results"]] == [second]
    with pytest.raises(ProlificRefused, match="is not a workspace of yours"):
        client.create_hook_secret("f" * 24)

    # Made disabled, with the X-Hook-Secret to confirm it by; a wrong secret is refused.
    headers, made = client.request(
        "POST",
        "hooks/subscriptions/",
        json={
            "event_type": "submission.status.change",
            "target_url": "https://study.example.org/prolific/webhook",
            "workspace_id": WORKSPACE_ID,
        },
        with_headers=True,
    )
    subscription = made["results"][0]
    assert subscription["is_enabled"] is False and headers["X-Hook-Secret"]
    assert client.subscriptions(WORKSPACE_ID) == []  # enabled ones only, by default
    with pytest.raises(ProlificRefused, match="not the X-Hook-Secret"):
        client.request(
            "POST", f"hooks/subscriptions/{subscription['id']}/", json={"secret": "guess"}
        )
    confirmed = client.request(
        "POST",
        f"hooks/subscriptions/{subscription['id']}/",
        json={"secret": headers["X-Hook-Secret"]},
    )
    assert confirmed["is_enabled"] is True
    assert [s["id"] for s in client.subscriptions(WORKSPACE_ID)] == [subscription["id"]]
    # The client does both steps.
    study_hook = client.subscribe(WORKSPACE_ID, "study.status.change", "https://x.example/hook")
    assert study_hook["is_enabled"] is True
    assert len(client.subscriptions(WORKSPACE_ID)) == 2
    assert client.hook_events(study_hook["id"]) == []
    with pytest.raises(ProlificRefused, match="event_type: one of"):
        client.subscribe(WORKSPACE_ID, "study.deleted", "https://x.example/hook")


@pytest.fixture
def study() -> StudyConfig:
    """A study run on Prolific (its completion code, its NO_CONSENT code)."""
    return study_config(
        completion={
            "mode": "prolific",
            "prolific_code": "C1A2B3C4",
            "prolific_no_consent_code": "NOCONSNT",
        }
    )


@pytest.fixture
def unset(db: Database) -> Settings:
    """The server's settings with no BAM_PROLIFIC_WEBHOOK_SECRET."""
    from tests.support.server import make_settings

    settings = make_settings(db.engine.url.render_as_string(hide_password=False))
    assert settings.prolific_webhook_secret is None
    return settings


@pytest.fixture
def server(
    db: Database, unset: Settings, study: StudyConfig, executor: ProcessPoolExecutor
) -> Iterator[tuple[str, httpx.Client]]:
    app = create_app(unset, study, db=db, executor=executor)
    with live(app) as base, httpx.Client(base_url=base, headers=ADMIN, timeout=60) as browser:
        yield base, browser


def participant_of(
    db: Database, base: str, browser: httpx.Client, study_id: str
) -> tuple[str, int]:
    """A participant takes a place on the replica and arrives at the study; their submission
    and participant id."""
    sent = browser.post(f"/prolific/studies/{study_id}/take-part", follow_redirects=False)
    assert sent.status_code == 303, sent.text
    link = httpx.URL(sent.headers["location"])
    ids = {key: link.params[key] for key in ("PROLIFIC_PID", "STUDY_ID", "SESSION_ID")}
    arrived = httpx.post(f"{base}/api/arrivals", json=ids)
    assert arrived.status_code == 201, arrived.text
    with db.read() as s:
        p = s.scalar(
            select(Participant).where(Participant.platform_submission_id == ids["SESSION_ID"])
        )
        assert p is not None
        return ids["SESSION_ID"], p.id


def test_return_on_the_replica_reaches_the_study_with_no_setting(
    server: tuple[str, httpx.Client], db: Database
) -> None:
    """Pressing Return on the replica, with BAM_PROLIFIC_WEBHOOK_SECRET not set: the replica
    signs with its own workspace secret, the server's webhook knows it, and the participant is
    returned on our side; a forged event is still refused."""
    base, browser = server
    client = ProlificClient(f"{base}/prolific/api/v1", ADMIN_TOKEN, first_wait=0.01)
    fields = draft()
    fields["external_study_url"] = fields["external_study_url"].replace("http://127.0.0.1", base)
    study_id = published(client, fields)
    submission, participant = participant_of(db, base, browser, study_id)
    returned = browser.post(f"/prolific/submissions/{submission}/return")
    assert returned.status_code == 303

    def released() -> bool:
        with db.read() as s:
            p = s.get(Participant, participant)
            return p is not None and p.status == "returned"

    wait_until(released, "the returned participant to be released")
    with db.read() as s:
        p = s.get(Participant, participant)
        assert p is not None and p.platform_status == "RETURNED"
        assert hook_secret(s) is not None  # made by the replica itself
    # The study's own status event arrived the same way.
    wait_until(
        lambda: any(
            v["study_id"] == study_id and v["status"] == "ACTIVE"
            for v in browser.get("/api/admin/prolific-studies").json()
        ),
        "the study's status event",
    )
    forged = httpx.post(
        f"{base}/prolific/webhook",
        content=b'{"event_type": "submission.status.change"}',
        headers={
            "X-Prolific-Request-Signature": "AAAA",
            "X-Prolific-Request-Timestamp": str(int(datetime.now(UTC).timestamp())),
            "X-Event-ID": "forged",
        },
    )
    assert forged.status_code == 401


def test_the_replica_records_each_delivery_to_a_subscription(
    server: tuple[str, httpx.Client], db: Database
) -> None:
    base, _ = server
    client = ProlificClient(f"{base}/prolific/api/v1", ADMIN_TOKEN, first_wait=0.01)
    client.create_hook_secret(WORKSPACE_ID)
    good = client.subscribe(WORKSPACE_ID, "study.status.change", f"{base}/prolific/webhook")
    bad = client.subscribe(WORKSPACE_ID, "study.status.change", f"{base}/no-such-hook")
    study_id = published(client)

    def delivered() -> bool:
        return all(
            [e["status"] for e in client.hook_events(s["id"])] != ["PENDING"]
            and client.hook_events(s["id"])
            for s in (good, bad)
        )

    wait_until(delivered, "both deliveries to be answered")
    [ok] = client.hook_events(good["id"])
    [failed] = client.hook_events(bad["id"])
    assert (ok["status"], failed["status"]) == ("SUCCEEDED", "FAILED")
    assert ok["resource_id"] == study_id and ok["payload"]["status"] == "ACTIVE"
    # A subscription to another event type gets none of them.
    other = client.subscribe(WORKSPACE_ID, "submission.status.change", f"{base}/prolific/webhook")
    client.transition_study(study_id, "PAUSE")
    wait_until(lambda: len(client.hook_events(good["id"])) == 2, "the pause's delivery")
    assert client.hook_events(other["id"]) == []


def test_the_replica_api_guesses_tokens_no_faster_than_the_sign_in(
    server: tuple[str, httpx.Client],
) -> None:
    base, _ = server
    wrong = {"Authorization": "Token not-the-token"}
    answers = [
        httpx.get(f"{base}/prolific/api/v1/workspaces/", headers=wrong).status_code
        for _ in range(12)
    ]
    assert answers[:10] == [401] * 10 and answers[10:] == [429, 429]
    limited = httpx.get(f"{base}/prolific/api/v1/workspaces/", headers=TOKEN)
    assert limited.status_code == 429 and "Retry-After" in limited.headers
    assert limited.json()["error"]["status"] == 429


# -- participant groups ---------------------------------------------------------------------------
def test_a_completion_code_adds_finishers_to_a_group_that_blocks_the_next_study(
    server: tuple[str, httpx.Client], db: Database
) -> None:
    base, browser = server
    client = ProlificClient(f"{base}/prolific/api/v1", ADMIN_TOKEN, first_wait=0.01)
    family = client.participant_group(WORKSPACE_ID, "BAM teaching")
    assert client.participant_group(WORKSPACE_ID, "BAM teaching") == family  # found, not made
    follow_up = client.participant_group(WORKSPACE_ID, "BAM follow-up")
    first = draft()
    first["completion_codes"][0]["actions"] += [
        {"action": "ADD_TO_PARTICIPANT_GROUP", "participant_group": family},
        {"action": "ADD_TO_PARTICIPANT_GROUP", "participant_group": follow_up},
    ]
    first["filters"] = [{"filter_id": "participant_group_blocklist", "selected_values": [family]}]
    study_id = published(client, first)
    sent = browser.post(f"/prolific/studies/{study_id}/take-part", follow_redirects=False)
    pid = httpx.URL(sent.headers["location"]).params["PROLIFIC_PID"]
    decliner = browser.post(f"/prolific/studies/{study_id}/take-part", follow_redirects=False)
    other = httpx.URL(decliner.headers["location"]).params["PROLIFIC_PID"]
    for who, code in ((pid, "C1A2B3C4"), (other, "NOCONSNT")):
        done = browser.get(
            "/prolific/submissions/complete",
            params={"cc": code},
            cookies={"prolific_replica_pid": who},
        )
        assert done.status_code == 200, done.text
    # The finisher joined both groups (the decliner's code adds no one).
    assert client.group_members(family) == [pid]
    assert client.group_members(follow_up) == [pid]
    listed = client.request("GET", f"participant-groups/{family}/")
    assert listed["participant_count"] == 1 and listed["feeder_studies"][0]["id"] == study_id

    # The next study of the family blocks them; a follow-up allows only them.
    second = published(client, first)
    barred = browser.post(
        f"/prolific/studies/{second}/take-part",
        params={"participant_id": pid},
        follow_redirects=False,
    )
    assert barred.status_code == 403 and "participant_group_blocklist" in barred.text
    allowed = browser.post(
        f"/prolific/studies/{second}/take-part",
        params={"participant_id": other},
        follow_redirects=False,
    )
    assert allowed.status_code == 303
    again = browser.post(
        f"/prolific/studies/{second}/take-part",
        params={"participant_id": other},
        follow_redirects=False,
    )
    assert again.status_code == 403 and "took part in it already" in again.text
    only = draft()
    only["filters"] = [{"filter_id": "participant_group_allowlist", "selected_values": [follow_up]}]
    third = published(client, only)
    assert (
        browser.post(
            f"/prolific/studies/{third}/take-part",
            params={"participant_id": other},
            follow_redirects=False,
        ).status_code
        == 403
    )
    assert (
        browser.post(
            f"/prolific/studies/{third}/take-part",
            params={"participant_id": pid},
            follow_redirects=False,
        ).status_code
        == 303
    )
    # A group that is not the workspace's is refused where a study names it.
    unknown = draft()
    unknown["filters"] = [
        {"filter_id": "participant_group_blocklist", "selected_values": ["e" * 24]}
    ]
    with pytest.raises(ProlificRefused, match=f"Participant group {'e' * 24} not found"):
        client.create_study(unknown)


def test_the_replicas_groups_are_added_to_and_taken_from(db: Database) -> None:
    client = replica_client(db)
    made = client.request(
        "POST",
        "participant-groups/",
        json={"workspace_id": WORKSPACE_ID, "name": "Pilot", "participant_ids": ["a" * 24]},
    )
    group = made["id"]
    assert client.add_to_group(group, ["b" * 24, "a" * 24]) == ["a" * 24, "b" * 24]
    left = client.request(
        "DELETE", f"participant-groups/{group}/participants/", json={"participant_ids": ["a" * 24]}
    )
    assert [m["participant_id"] for m in left["results"]] == ["b" * 24]
    with pytest.raises(ProlificRefused, match="participant_ids: a list of participant ids"):
        client.add_to_group(group, ["not an id"])


# -- scheduled publishing and the concurrency --------------------------------------------------------
def test_a_study_scheduled_to_publish_is_published_at_its_time(db: Database) -> None:
    client = replica_client(db)
    study = client.create_study(draft())
    with pytest.raises(ProlificRefused, match="publish_at: required"):
        client.transition_study(study["id"], "SCHEDULE_PUBLISH")
    past = (datetime.now(UTC) - timedelta(minutes=1)).isoformat()
    with pytest.raises(ProlificRefused, match="publish_at: a time in the future"):
        client.schedule_publish(study["id"], past)
    soon = (datetime.now(UTC) + timedelta(hours=1)).isoformat()
    scheduled = client.schedule_publish(study["id"], soon)
    assert scheduled["status"] == "SCHEDULED"
    assert datetime.fromisoformat(scheduled["publish_at"]) == datetime.fromisoformat(soon)
    assert client.transition_study(study["id"], "CANCEL_PUBLISH")["status"] == "UNPUBLISHED"
    client.schedule_publish(study["id"], soon)
    assert client.get_study(study["id"])["status"] == "SCHEDULED"
    # Its time comes: published at it.
    with db.write() as s:
        row = s.get(ProlificReplicaStudy, study["id"])
        assert row is not None
        row.fields = {**row.fields, "publish_at": past}
    now = client.get_study(study["id"])
    assert now["status"] == "ACTIVE"
    assert datetime.fromisoformat(now["published_at"]) == datetime.fromisoformat(past)


def test_a_published_studys_concurrency_is_patched_but_not_its_reward(db: Database) -> None:
    client = replica_client(db)
    study_id = published(client)
    changed = client.set_max_concurrent(study_id, 4)
    assert changed["submissions_config"]["max_concurrent_submissions"] == 4
    assert client.get_study(study_id)["submissions_config"] == {"max_concurrent_submissions": 4}
    with pytest.raises(ProlificRefused, match="max_concurrent_submissions is -1"):
        client.set_max_concurrent(study_id, 0)
    with pytest.raises(ProlificRefused, match="Only total_available_places, internal_name"):
        client.request("PATCH", f"studies/{study_id}/", json={"reward": 1})


# -- a pay Prolific accepted is not paid yet ------------------------------------------------------------
class AcceptsPay(httpx.BaseTransport):
    """The replica's API, except that ``pay`` answers 202 and pays only when ``settle`` is
    called (Prolific pays asynchronously)."""

    def __init__(self, inner: httpx.BaseTransport) -> None:
        self.inner = inner
        self.accepted: list[httpx.Request] = []

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        if not request.url.path.endswith("/pay/"):
            return self.inner.handle_request(request)
        self.accepted.append(request)
        return httpx.Response(202)

    def settle(self) -> None:
        for request in self.accepted:
            assert self.inner.handle_request(request).status_code == 202
        self.accepted = []


@pytest.fixture
def test_client(
    db: Database, unset: Settings, study: StudyConfig, executor: ProcessPoolExecutor
) -> Iterator[TestClient]:
    with TestClient(create_app(unset, study, db=db, executor=executor)) as client:
        yield client


def test_a_pay_prolific_accepted_is_in_doubt_until_its_record_lists_it(
    test_client: TestClient, db: Database
) -> None:
    participant, _, _ = prolific_participant(test_client, db)
    transport = AcceptsPay(ReplicaTransport(db, ADMIN_TOKEN))
    backend = ProlificBackend(replica_client(db, transport), "GBP", name="prolific-replica")

    def pay(token: str) -> bool:
        return review.pay_bonus(db, backend, participant, Decimal("1.50"), "Taught well", token)

    assert pay("tok-202") is False  # accepted, not paid yet
    assert state_of(db, "tok-202") == "in_doubt" and payments(db) == []
    assert review.reconcile_bonuses(db, backend) == []  # not on the record: not paid again
    # The dashboard shows it in doubt, not paid.
    detail = test_client.get(f"/api/admin/participants/{participant}", headers=ADMIN).json()
    [shown] = detail["bonuses"]
    assert shown["state"] == "in_doubt" and shown["paid_at"] is None
    transport.settle()  # Prolific pays
    assert review.reconcile_bonuses(db, backend) == ["tok-202"]
    assert state_of(db, "tok-202") == "paid" and payments(db) == [150]
    assert pay("tok-202") is False and payments(db) == [150]

    # One Prolific never pays: paid again, once, after the time Prolific takes.
    assert pay("tok-lost") is False
    transport.accepted = []  # lost
    # (every pay of that amount to the submission counts: the one that paid may be listed late)
    age(db, "tok-202", review.PAY_SETTLES_WITHIN)
    age(db, "tok-lost", review.PAY_SETTLES_WITHIN)
    assert review.reconcile_bonuses(db, backend) == []  # its pay is accepted again, not listed
    assert state_of(db, "tok-lost") == "in_doubt"
    transport.settle()
    assert review.reconcile_bonuses(db, backend) == ["tok-lost"]
    assert payments(db) == [150, 150]
    with db.read() as s:
        assert [b.state for b in s.scalars(select(Bonus).order_by(Bonus.id))] == ["paid", "paid"]
