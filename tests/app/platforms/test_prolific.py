"""Prolific: the study server's client against the local replica over real HTTP (Prolific's
paths, fields, statuses and refusals), the client's retries and messages, and the dashboard's
review of Prolific participants through the one review interface, with every money action
carried out once even when the server dies between a bonus's set-up and its payment."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from datetime import timedelta
from decimal import Decimal
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from server.app.errors import ApiError
from server.app.export.tables import export_tables
from server.app.main import create_app
from server.app.platforms import review
from server.app.platforms.prolific import (
    ProlificBackend,
    ProlificClient,
    ProlificRefused,
    ProlificUnavailable,
)
from server.app.platforms.prolific_replica import ReplicaTransport, Workspace
from server.app.platforms.review import Reviewed
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import Bonus, Participant
from server.app.storage.replica_models import (
    ProlificReplicaBonusSetup,
    ProlificReplicaPayment,
    ProlificReplicaSubmission,
)
from server.app.study_file import StudyConfig, StudyConfigError
from tests.support.server import ADMIN_TOKEN, live, study_config

ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
BASE = "/api/admin/participants"
REASON = (
    "The agents were not taught: no demonstration was given in any of the six tasks, and the "
    "study's instructions asked for one in each."
)
assert len(REASON) >= 100


def draft(places: int = 3) -> dict[str, Any]:
    """A study as ``bam-study prolific create`` makes it."""
    return {
        "name": "Teaching robots",
        "internal_name": "bam-study rehearsal",
        "description": "Teach simulated robots in a grid world with the arrow keys.",
        "external_study_url": "http://127.0.0.1/study?PROLIFIC_PID={{%PROLIFIC_PID%}}"
        "&STUDY_ID={{%STUDY_ID%}}&SESSION_ID={{%SESSION_ID%}}",
        "prolific_id_option": "url_parameters",
        "completion_codes": [
            {
                "code": "C1A2B3C4",
                "code_type": "COMPLETED",
                "actions": [{"action": "MANUALLY_REVIEW"}],
            },
            {
                "code": "NOCONSNT",
                "code_type": "NO_CONSENT",
                "actions": [{"action": "REQUEST_RETURN", "return_reason": "You did not consent."}],
            },
        ],
        "total_available_places": places,
        "estimated_completion_time": 30,
        "maximum_allowed_time": 90,
        "reward": 600,
        "device_compatibility": ["desktop"],
    }


@pytest.fixture
def replica(
    db: Database, settings: Settings, study: StudyConfig, executor: ProcessPoolExecutor
) -> Iterator[tuple[str, httpx.Client]]:
    """The server on a real port; a browser signed in with the admin token (to take part)."""
    app = create_app(settings, study, db=db, executor=executor)
    with live(app) as base, httpx.Client(base_url=base, headers=ADMIN) as browser:
        yield base, browser


def take_part(browser: httpx.Client, study_id: str, code: str | None = "C1A2B3C4") -> str:
    """A participant takes a place (sent to the external URL with the placeholders filled)
    and, with ``code``, comes back through the completion redirect; the submission id."""
    sent = browser.post(f"/prolific/studies/{study_id}/take-part", follow_redirects=False)
    assert sent.status_code == 303, sent.text
    target = httpx.URL(sent.headers["location"])
    assert target.params["STUDY_ID"] == study_id
    pid, submission = target.params["PROLIFIC_PID"], target.params["SESSION_ID"]
    assert len(pid) == 24 and len(submission) == 24
    if code is not None:
        done = browser.get(
            "/prolific/submissions/complete",
            params={"cc": code},
            cookies={"prolific_replica_pid": pid},
        )
        assert done.status_code == 200, done.text
    return submission


def test_the_client_runs_a_study_on_the_replica_over_http(
    replica: tuple[str, httpx.Client], db: Database
) -> None:
    base, browser = replica
    client = ProlificClient(f"{base}/prolific/api/v1", ADMIN_TOKEN, first_wait=0.01)
    study = client.create_study(draft(places=3))
    assert (study["status"], study["reward"], study["total_available_places"]) == (
        "UNPUBLISHED",
        600,
        3,
    )
    # A draft takes no one; a published study does.
    assert browser.post(f"/prolific/studies/{study['id']}/take-part").status_code == 409
    assert client.transition_study(study["id"], "PUBLISH")["status"] == "ACTIVE"
    first, second = take_part(browser, study["id"]), take_part(browser, study["id"])
    third = take_part(browser, study["id"], code=None)
    # Every place taken: the study awaits review (as Prolific). A return frees a place, but
    # the full study does not reopen by itself: the researcher sends START to replace it.
    assert client.get_study(study["id"])["status"] == "AWAITING REVIEW"
    returned = browser.post(f"/prolific/submissions/{third}/return", follow_redirects=False)
    assert returned.status_code == 303, returned.text
    assert client.get_study(study["id"])["status"] == "AWAITING REVIEW"
    assert browser.post(f"/prolific/studies/{study['id']}/take-part").status_code == 409
    assert client.transition_study(study["id"], "START")["status"] == "ACTIVE"
    with pytest.raises(ProlificRefused, match="can only go up"):
        client.set_places(study["id"], 2)
    assert client.set_places(study["id"], 4)["total_available_places"] == 4

    # Listed page by page, for this study only, in the order they started (ordering=started_at);
    # the status filter spells statuses as Prolific's does.
    listed = list(client.submissions(study["id"], page_size=2))
    assert [x["id"] for x in listed] == [first, second, third]
    assert {x["id"]: x["status"] for x in listed}[third] == "RETURNED"
    newest = client.request(
        "GET", "submissions/", params={"study": study["id"], "ordering": "-started_at"}
    )
    assert [x["id"] for x in newest["results"]] == [third, second, first]
    awaiting = client.request(
        "GET",
        "submissions/",
        params={"study": study["id"], "status": "AWAITING_REVIEW", "page_size": 1},
    )
    assert [x["id"] for x in awaiting["results"]] == [first]
    assert "status=AWAITING_REVIEW" in awaiting["_links"]["next"]["href"]

    # Approve, reject (Prolific's refusals first), bulk approve.
    client.transition_submission(study["id"], first, "APPROVE")
    client.transition_submission(study["id"], first, "APPROVE")  # idempotent
    with pytest.raises(ProlificRefused, match=r"400.*at least 100 characters"):
        client.transition_submission(
            study["id"], second, "REJECT", message="Too short.", rejection_category="NO_DATA"
        )
    with pytest.raises(ProlificRefused, match="rejection_category"):
        client.transition_submission(
            study["id"], second, "REJECT", message=REASON, rejection_category="RUDE"
        )
    with pytest.raises(ProlificRefused, match="RETURNED cannot be approved"):
        client.transition_submission(study["id"], third, "APPROVE")
    client.transition_submission(
        study["id"], second, "REJECT", message=REASON, rejection_category="NO_DATA"
    )
    assert client.submission(study["id"], second)["status"] == "REJECTED"
    with pytest.raises(ProlificRefused, match="404"):
        client.submission(study["id"], "0" * 24)

    # Bonuses: set up, then pay; Prolific's pay is not idempotent, nor is the replica's.
    setup = client.set_up_bonuses(study["id"], [(listed[0]["participant_id"], "1.50")])
    assert setup["amount"] == 150 and set(setup) >= {"id", "amount", "fees", "vat", "total_amount"}
    assert client.bonus_payments(study["id"], first) == []
    client.pay_bonuses(setup["id"])
    client.pay_bonuses(setup["id"])
    with db.read() as s:
        assert list(s.scalars(select(ProlificReplicaPayment.amount))) == [150, 150]
    # The submission lists the bonuses paid on it, in cents (SubmissionDetail.bonus_payments).
    assert client.bonus_payments(study["id"], first) == [150, 150]
    assert client.submission(study["id"], first)["bonus_payments"] == [150, 150]
    assert client.bonus_payments(study["id"], second) == []
    with pytest.raises(ProlificRefused, match="did not take part"):
        client.set_up_bonuses(study["id"], [("f" * 24, "1.00")])

    # Without the token nothing is answered; the token is in no message and no repr.
    stranger = ProlificClient(f"{base}/prolific/api/v1", "wrong-token")
    with pytest.raises(ProlificRefused, match="401") as refused:
        stranger.get_study(study["id"])
    assert "wrong-token" not in str(refused.value) and "wrong-token" not in repr(stranger)
    with pytest.raises(ProlificRefused, match="study: a study id is required"):
        client.request("GET", "submissions/")
    client.close()


def test_the_replicas_workspace_pays_rewards_and_bonuses_from_its_balance(
    replica: tuple[str, httpx.Client],
) -> None:
    base, browser = replica
    client = ProlificClient(f"{base}/prolific/api/v1", ADMIN_TOKEN)
    study = client.create_study(draft(places=2))  # 2 places at 6.00
    workspace = client.workspace_of(study)
    start = client.balance(workspace)
    assert start == {"currency_code": "GBP", "total_balance": 100_000, "available_balance": 100_000}
    # The cost calculator: the rewards with Prolific's fee (33.3%).
    assert client.study_cost(600, 2) == 1600
    with pytest.raises(ProlificRefused, match="400"):
        client.request("POST", "study-cost-calculator/", json={"reward": 600})
    assert client.least_hourly_reward(workspace, "GBP") == 600
    assert client.least_hourly_reward(workspace, "USD") == 800
    with pytest.raises(ProlificRefused, match="workspace_id"):
        client.request("GET", "reward-recommendations/", params={"currency": "GBP"})
    # Published: its cost is held, not yet paid.
    client.transition_study(study["id"], "PUBLISH")
    assert client.balance(workspace)["available_balance"] == 100_000 - 1600
    assert client.balance(workspace)["total_balance"] == 100_000
    # An approval pays one reward with its fee; a bonus paid, the same.
    submission = take_part(browser, study["id"])
    client.transition_submission(study["id"], submission, "APPROVE")
    assert client.balance(workspace) == {
        "currency_code": "GBP",
        "total_balance": 100_000 - 800,
        "available_balance": 100_000 - 1600,
    }
    paid_to = client.submission(study["id"], submission)["participant_id"]
    client.pay_bonuses(client.set_up_bonuses(study["id"], [(paid_to, "1.50")])["id"])
    assert client.balance(workspace)["total_balance"] == 100_000 - 800 - 200
    # Stopped: what it held for the place never taken is available again.
    client.transition_study(study["id"], "STOP")
    assert client.balance(workspace)["available_balance"] == 100_000 - 1000
    with pytest.raises(ProlificRefused, match="404"):
        client.balance("0" * 24)
    client.close()


def scripted(answers: list[Any], seen: list[httpx.Request]) -> httpx.MockTransport:
    def answer(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        reply = answers.pop(0)
        if isinstance(reply, Exception):
            raise reply
        return reply

    return httpx.MockTransport(answer)


def test_the_client_retries_429_and_5xx_with_back_off_but_never_resends_pay() -> None:
    seen: list[httpx.Request] = []
    waits: list[float] = []
    answers: list[Any] = [
        httpx.Response(429, headers={"Retry-After": "2"}),
        httpx.Response(503),
        httpx.ConnectError("refused"),
        httpx.Response(200, json={"id": "a" * 24, "status": "ACTIVE"}),
    ]
    client = ProlificClient(
        "https://api.prolific.test/api/v1",
        "secret-token-xyz",
        transport=scripted(answers, seen),
        sleep=waits.append,
    )
    assert client.get_study("a" * 24)["status"] == "ACTIVE"
    assert waits == [2.0, 4.0, 8.0]  # Retry-After honoured, then doubled
    assert all(r.headers["Authorization"] == "Token secret-token-xyz" for r in seen)
    assert str(seen[0].url) == f"https://api.prolific.test/api/v1/studies/{'a' * 24}/"

    seen.clear()
    client = ProlificClient(
        "https://api.prolific.test/api/v1",
        "secret-token-xyz",
        transport=scripted([httpx.Response(502)], seen),
        sleep=waits.append,
    )
    with pytest.raises(ProlificUnavailable, match="502") as failed:
        client.pay_bonuses("b" * 24)
    assert len(seen) == 1 and "secret-token-xyz" not in str(failed.value)

    # A bonus set-up after a 5xx may exist: reported, not set up a second time.
    seen.clear()
    client = ProlificClient(
        "https://api.prolific.test/api/v1",
        "t",
        transport=scripted([httpx.Response(503)], seen),
        sleep=waits.append,
    )
    with pytest.raises(ProlificUnavailable, match="it may have been made"):
        client.set_up_bonuses("c" * 24, [("d" * 24, "1.00")])
    assert len(seen) == 1

    refusal = httpx.Response(
        400, json={"error": {"status": 400, "detail": "Insufficient balance to pay."}}
    )
    client = ProlificClient(
        "https://api.prolific.test/api/v1", "t", transport=scripted([refusal], seen)
    )
    with pytest.raises(ProlificRefused, match="Insufficient balance to pay"):
        client.set_up_bonuses("c" * 24, [("d" * 24, "1.00")])


class Crash(BaseException):
    """The server process dying at this point."""


class CrashesAroundPay(ProlificBackend):
    """Dies once: right after Prolific set the bonus up (``set-up``), right before Prolific's
    pay is sent (``before``), or right after it was sent (``after``)."""

    def __init__(self, backend: ProlificBackend, when: str) -> None:
        super().__init__(backend.client, backend.currency, backend.name)
        self.when = when

    def set_up_bonus(self, who: Reviewed, amount: str, reason: str) -> str | None:
        made = super().set_up_bonus(who, amount, reason)
        if self.when == "set-up":
            raise Crash
        return made

    def pay_bonus(self, who: Reviewed, amount: str, reason: str, token: str, setup_id: Any) -> None:
        if self.when == "before":
            raise Crash
        super().pay_bonus(who, amount, reason, token, setup_id)
        if self.when == "after":
            raise Crash


def prolific_participant(
    client: TestClient, db: Database, places: int = 3
) -> tuple[int, str, dict[str, Any]]:
    """A Prolific participant of a study on the replica who completed it (AWAITING REVIEW)."""
    made = client.post(
        "/prolific/api/v1/studies/",
        json=draft(places),
        headers={"Authorization": f"Token {ADMIN_TOKEN}"},
    )
    assert made.status_code == 201, made.text
    study = made.json()
    published = client.post(
        f"/prolific/api/v1/studies/{study['id']}/transition/",
        json={"action": "PUBLISH"},
        headers={"Authorization": f"Token {ADMIN_TOKEN}"},
    )
    assert published.status_code == 200
    sent = client.post(
        f"/prolific/studies/{study['id']}/take-part", headers=ADMIN, follow_redirects=False
    )
    target = httpx.URL(sent.headers["location"])
    pid, submission = target.params["PROLIFIC_PID"], target.params["SESSION_ID"]
    client.cookies.set("prolific_replica_pid", pid)
    assert (
        client.get("/prolific/submissions/complete", params={"cc": "C1A2B3C4"}).status_code == 200
    )
    with db.write() as s:
        p = Participant(
            token_hash=os.urandom(32).hex(),
            platform="prolific",
            platform_participant_id=pid,
            platform_submission_id=submission,
            platform_study_id=study["id"],
            status="submitted",
        )
        s.add(p)
        s.flush()
        return p.id, submission, study


def payments(db: Database) -> list[int]:
    with db.read() as s:
        return list(s.scalars(select(ProlificReplicaPayment.amount)))


def test_the_dashboard_reviews_prolific_participants_on_the_replica(
    client: TestClient, db: Database
) -> None:
    participant, submission, _ = prolific_participant(client, db)
    # Prolific's rules are checked here first, with a clear 422.
    short = client.post(
        f"{BASE}/{participant}/rejection",
        json={"message": "Too short", "rejection_category": "NO_DATA"},
        headers=ADMIN,
    )
    assert short.status_code == 422 and "at least 100" in short.text
    nameless = client.post(
        f"{BASE}/{participant}/rejection", json={"message": REASON}, headers=ADMIN
    )
    assert nameless.status_code == 422 and "rejection_category" in nameless.text
    approved = client.post(f"{BASE}/{participant}/approval", json={}, headers=ADMIN)
    assert approved.status_code == 200, approved.text
    assert approved.json()["review"]["backend"] == "prolific-replica"
    with db.read() as s:
        assert s.get(ProlificReplicaSubmission, submission).status == "APPROVED"  # type: ignore[union-attr]
    bonus = {"amount": "0.75", "reason": "Taught well", "unique_token": "prolific-bonus-1"}
    for _ in range(3):  # the first pays, the repeats answer the same
        paid = client.post(f"{BASE}/{participant}/bonuses", json=bonus, headers=ADMIN)
        assert paid.status_code == 200, paid.text
    assert [(b["amount"], b["currency"], b["state"]) for b in paid.json()["bonuses"]] == [
        ("0.75", "GBP", "paid")
    ]
    assert payments(db) == [75]
    exported = export_tables(db)["bonuses"]
    assert list(exported["setup_id"]) == [paid.json()["bonuses"][0]["setup_id"]]


def test_a_crash_around_a_prolific_bonus_never_pays_twice(client: TestClient, db: Database) -> None:
    participant, _, _ = prolific_participant(client, db)
    backend = client.app.state.server.review_backend("prolific")  # type: ignore[attr-defined]

    def pay(token: str, amount: str, crash: str | None = None) -> bool:
        used = backend if crash is None else CrashesAroundPay(backend, crash)
        return review.pay_bonus(db, used, participant, Decimal(amount), "Well taught", token)

    # Killed after Prolific set the bonus up, before its id was stored: that set-up is never
    # paid; the retry sets up again and pays once.
    with pytest.raises(Crash):
        pay("tok-setup-1", "2", "set-up")
    assert payments(db) == []
    assert pay("tok-setup-1", "2") is True
    assert pay("tok-setup-1", "2") is False
    assert payments(db) == [200]
    # Killed as pay was about to be sent, or after it was sent: the outcome is unknown, so
    # pay is not sent again (Prolific's pay is not idempotent) until Prolific's record of the
    # submission's bonuses settles it.
    for token, when, paid in (("tok-after-1", "after", [200, 100]), ("tok-before-1", "before", [])):
        with pytest.raises(Crash):
            pay(token, "1", when)
        assert state_of(db, token) == "paying"
        # Moments later the pay may still be on its way: answered at once, nothing sent.
        started = time.monotonic()
        with pytest.raises(ApiError, match="is being paid now") as early:
            pay(token, "1")
        assert early.value.status == 409 and time.monotonic() - started < 5
        # Past the pay call's limit: Prolific's record settles it.
        age(db, token, review.PAY_CALL_LIMIT)
        if paid:
            assert pay(token, "1") is False  # Prolific lists it: paid, not paid again
            assert state_of(db, token) == "paid" and payments(db) == paid
    # Not on Prolific's record: in doubt until Prolific has had the time it takes to pay.
    with pytest.raises(ApiError, match="does not list it among the submission's bonuses yet"):
        pay("tok-before-1", "1")
    assert payments(db) == [200, 100]
    # (every pay of that amount to the submission counts: the one that paid may not be
    # listed yet either)
    age(db, "tok-before-1", review.PAY_SETTLES_WITHIN)
    with pytest.raises(ApiError, match="does not list it"):
        pay("tok-before-1", "1")
    age(db, "tok-after-1", review.PAY_SETTLES_WITHIN)
    assert review.reconcile_bonuses(db, backend) == ["tok-before-1"]  # paid now, once
    assert payments(db) == [200, 100, 100]
    assert pay("tok-before-1", "1") is False
    assert review.reconcile_bonuses(db, backend) == []
    assert payments(db) == [200, 100, 100]


def state_of(db: Database, token: str) -> str:
    with db.read() as s:
        return str(s.scalar(select(Bonus.state).where(Bonus.unique_token == token)))


def age(db: Database, token: str, by: timedelta) -> None:
    """Time passes: the bonus's pay was sent ``by`` (and a second) earlier than recorded."""
    with db.write() as s:
        row = s.scalar(select(Bonus).where(Bonus.unique_token == token))
        assert row is not None and row.pay_sent_at is not None
        row.pay_sent_at -= by + timedelta(seconds=1)


class FailingPay(httpx.BaseTransport):
    """The replica's API, except that Prolific's ``pay`` goes wrong once: it pays and then
    answers 429 or 400, or the answer is lost (a read time-out), or it answers 429 without
    paying."""

    def __init__(self, inner: httpx.BaseTransport, fault: str) -> None:
        self.inner = inner
        self.fault: str | None = fault

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        if not request.url.path.endswith("/pay/") or self.fault is None:
            return self.inner.handle_request(request)
        fault, self.fault = self.fault, None
        if fault != "429":
            paid = self.inner.handle_request(request)
            assert paid.status_code == 202
        if fault == "timeout":
            raise httpx.ReadTimeout("The read operation timed out", request=request)
        if fault == "paid-400":
            return httpx.Response(400, json={"error": {"detail": "Something went wrong."}})
        return httpx.Response(429, json={"error": {"detail": "Too many requests."}})


def failing_pay(db: Database, fault: str) -> ProlificBackend:
    """The replica's review backend, its ``pay`` going wrong once as ``fault`` says."""
    return ProlificBackend(
        ProlificClient(
            "http://replica/prolific/api/v1",
            ADMIN_TOKEN,
            transport=FailingPay(ReplicaTransport(db, ADMIN_TOKEN), fault),
        ),
        "GBP",
        name="prolific-replica",
    )


@pytest.mark.parametrize(
    ("fault", "status", "paid_by_it"),
    [("paid-429", 502, True), ("timeout", 502, True), ("paid-400", 409, True), ("429", 502, False)],
)
def test_a_prolific_bonus_whose_pay_failed_is_in_doubt_until_prolifics_record_settles_it(
    client: TestClient, db: Database, fault: str, status: int, paid_by_it: bool
) -> None:
    participant, _, _ = prolific_participant(client, db)
    failing = failing_pay(db, fault)
    with pytest.raises(ApiError, match="is in doubt") as failed:
        review.pay_bonus(db, failing, participant, Decimal("1.25"), "Taught well", "tok-doubt")
    assert failed.value.status == status
    assert payments(db) == ([125] if paid_by_it else [])
    # Shown as in doubt (neither paid nor unpaid), with how it settles.
    shown = client.get(f"{BASE}/{participant}", headers=ADMIN).json()["bonuses"]
    assert [(b["state"], b["paid_at"]) for b in shown] == [("in_doubt", None)]
    assert "settled from Prolific's record" in shown[0]["note"]
    assert shown[0]["pay_sent_at"] is not None
    # A fresh form (a new request token) cannot pay it a second time meanwhile.
    fresh = {"amount": "1.25", "reason": "Taught well", "unique_token": "tok-fresh"}
    refused = client.post(f"{BASE}/{participant}/bonuses", json=fresh, headers=ADMIN)
    assert refused.status_code == 409 and "whose payment is in doubt" in refused.text
    resend = {"amount": "1.25", "reason": "Taught well", "unique_token": "tok-doubt"}
    if paid_by_it:
        # Prolific lists it on the submission: a resend settles it as paid, pays nothing.
        settled = client.post(f"{BASE}/{participant}/bonuses", json=resend, headers=ADMIN)
        assert settled.status_code == 200, settled.text
        assert [b["state"] for b in settled.json()["bonuses"]] == ["paid"]
    else:
        # Not listed: unpaid only once Prolific has had the time it takes to pay.
        early = client.post(f"{BASE}/{participant}/bonuses", json=resend, headers=ADMIN)
        assert early.status_code == 409 and "does not list it" in early.text
        assert payments(db) == []
        age(db, "tok-doubt", review.PAY_SETTLES_WITHIN)
        settled = client.post(f"{BASE}/{participant}/bonuses", json=resend, headers=ADMIN)
        assert settled.status_code == 200, settled.text
    assert payments(db) == [125]
    again = client.post(f"{BASE}/{participant}/bonuses", json=resend, headers=ADMIN)
    assert again.status_code == 200 and payments(db) == [125]
    assert client.post("/api/admin/reconciliation", headers=ADMIN).json()["settled_bonuses"] == []
    # Settled: a new bonus is taken again.
    assert (
        client.post(f"{BASE}/{participant}/bonuses", json=fresh, headers=ADMIN).status_code == 200
    )
    assert payments(db) == [125, 125]


def test_concurrent_resends_of_a_bonus_in_doubt_pay_it_once(
    client: TestClient, db: Database
) -> None:
    participant, _, _ = prolific_participant(client, db)
    failing = failing_pay(db, "429")
    with pytest.raises(ApiError, match="is in doubt"):
        review.pay_bonus(db, failing, participant, Decimal("3"), "Taught well", "tok-many")
    age(db, "tok-many", review.PAY_SETTLES_WITHIN)  # not on Prolific's record: unpaid
    backend = client.app.state.server.review_backend("prolific")  # type: ignore[attr-defined]
    answers: list[Any] = []

    def resend() -> None:
        try:
            answers.append(
                review.pay_bonus(db, backend, participant, Decimal("3"), "Taught well", "tok-many")
            )
        except ApiError as error:
            answers.append(error.status)

    threads = [threading.Thread(target=resend) for _ in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60)
    assert len(answers) == 8 and answers.count(True) == 1, answers
    assert set(answers) <= {True, False, 409}
    assert payments(db) == [300] and state_of(db, "tok-many") == "paid"


def test_the_reconciliation_settles_a_prolific_bonus_in_doubt_from_prolifics_record(
    client: TestClient, db: Database
) -> None:
    participant, _, _ = prolific_participant(client, db)
    failing = failing_pay(db, "paid-429")
    # Two bonuses of the same amount: one paid (202), one in doubt that Prolific did pay.
    assert review.pay_bonus(db, client.app.state.server.review_backend("prolific"), participant, Decimal("2"), "First", "tok-a")  # type: ignore[attr-defined]  # fmt: skip
    with pytest.raises(ApiError, match="is in doubt"):
        review.pay_bonus(db, failing, participant, Decimal("2"), "Second", "tok-b")
    assert payments(db) == [200, 200]
    done = client.post("/api/admin/reconciliation", headers=ADMIN)
    assert done.status_code == 200 and done.json()["settled_bonuses"] == ["tok-b"]
    assert state_of(db, "tok-b") == "paid" and payments(db) == [200, 200]


PROLIFIC_TABLE = {
    "name": "Teaching robots",
    "description": "Teach simulated robots in a grid world with the arrow keys.",
    "places": 3,
    "reward": 6,
    "estimated_minutes": 30,
    "maximum_minutes": 90,
    "public_url": "https://study.example.org",
}


def test_bonuses_may_not_pass_the_study_files_budget(
    db: Database, settings: Settings, executor: ProcessPoolExecutor
) -> None:
    study = study_config(
        completion={"mode": "prolific", "prolific_code": "C1A2B3C4"},
        prolific={**PROLIFIC_TABLE, "bonus_budget": 3},
    )
    with TestClient(create_app(settings, study, db=db, executor=executor)) as client:
        participant, _, _ = prolific_participant(client, db)
        other, _, _ = prolific_participant(client, db)

        def bonus(who: int, amount: str, token: str) -> httpx.Response:
            body = {"amount": amount, "reason": "Taught well", "unique_token": token}
            return client.post(f"{BASE}/{who}/bonuses", json=body, headers=ADMIN)

        assert bonus(participant, "2.00", "budget-tok-1").status_code == 200
        # 2.00 + 1.50 would pass 3.00: refused before anything is recorded or sent.
        over = bonus(other, "1.50", "budget-tok-2")
        assert over.status_code == 409
        assert "would take the study's bonuses to 3.50" in over.text
        assert "past its budget of 3.00" in over.text and "1.00 is left" in over.text
        assert payments(db) == [200] and len(our_tokens(db)) == 1
        assert bonus(other, "1.00", "budget-tok-3").status_code == 200  # up to the budget itself
        assert bonus(other, "1.00", "budget-tok-3").status_code == 200  # a resend is no new bonus
        assert "0.00 is left" in bonus(participant, "0.01", "budget-tok-4").text
        assert payments(db) == [200, 100] and our_tokens(db) == ["budget-tok-1", "budget-tok-3"]
    with pytest.raises(StudyConfigError, match="bonus_budget"):
        study_config(completion={"mode": "prolific", "prolific_code": "C"}, prolific={**PROLIFIC_TABLE, "bonus_budget": 0})  # fmt: skip


def test_a_bonus_in_another_currency_than_the_workspaces_is_refused_before_it_is_set_up(
    client: TestClient, db: Database
) -> None:
    participant, _, _ = prolific_participant(client, db)
    # The workspace pays in USD; the server is set for GBP (BAM_PROLIFIC_CURRENCY).
    usd = ReplicaTransport(db, ADMIN_TOKEN, workspace=Workspace("USD", 100_000))
    backend = ProlificBackend(
        ProlificClient("http://replica/prolific/api/v1", ADMIN_TOKEN, transport=usd),
        "GBP",
        name="prolific-replica",
    )
    for _ in range(2):  # read once, refused each time
        with pytest.raises(ApiError, match="pays in USD, but BAM_PROLIFIC_CURRENCY is GBP") as no:
            review.pay_bonus(db, backend, participant, Decimal("1"), "Taught well", "cur-tok-1")
        assert no.value.status == 409
    assert payments(db) == [] and our_tokens(db) == []
    with db.read() as s:
        assert s.scalars(select(ProlificReplicaBonusSetup)).all() == []


def our_tokens(db: Database) -> list[str]:
    with db.read() as s:
        return list(s.scalars(select(Bonus.unique_token).order_by(Bonus.id)))


def test_the_client_pages_submissions_in_the_order_they_started_and_names_where_it_failed() -> None:
    """``ordering=started_at`` keeps each page stable while submissions arrive (an unordered
    page can skip or repeat one); an unreachable API is named in the error."""
    sent: list[httpx.URL] = []

    def answer(request: httpx.Request) -> httpx.Response:
        sent.append(request.url)
        return httpx.Response(200, json={"results": [{"id": "s1"}], "_links": {"next": None}})

    client = ProlificClient(
        "https://prolific.test/api/v1", "t", transport=httpx.MockTransport(answer)
    )
    assert [x["id"] for x in client.submissions("a" * 24)] == ["s1"]
    assert sent[0].params["ordering"] == "started_at" and sent[0].params["study"] == "a" * 24

    def refuse(request: httpx.Request) -> httpx.Response:
        raise httpx.ConnectError("refused", request=request)

    down = ProlificClient(
        "http://127.0.0.1:9/prolific/api/v1",
        "t",
        attempts=1,
        transport=httpx.MockTransport(refuse),
    )
    with pytest.raises(ProlificUnavailable, match=r"http://127\.0\.0\.1:9/prolific/api/v1/"):
        down.get_study("a" * 24)


def test_a_draft_is_resent_only_where_prolific_cannot_have_made_it() -> None:
    """A 429 or a connection that never opened is resent; a 503 may come after the draft was
    made, so it is reported, with what to check, and no second draft is asked for."""
    seen: list[httpx.Request] = []
    answers: list[Any] = [
        httpx.Response(429),
        httpx.ConnectError("refused"),
        httpx.Response(201, json={"id": "a" * 24, "status": "UNPUBLISHED"}),
    ]
    client = ProlificClient(
        "https://api.prolific.test/api/v1",
        "t",
        transport=scripted(answers, seen),
        sleep=lambda _: None,
    )
    assert client.create_study({"name": "x"})["id"] == "a" * 24 and len(seen) == 3

    seen.clear()
    answers = [httpx.Response(503), httpx.Response(201, json={"id": "b" * 24})]
    client = ProlificClient(
        "https://api.prolific.test/api/v1",
        "t",
        transport=scripted(answers, seen),
        sleep=lambda _: None,
    )
    with pytest.raises(ProlificUnavailable, match=r"503.*look on Prolific before sending it again"):
        client.create_study({"name": "x"})
    assert len(seen) == 1
