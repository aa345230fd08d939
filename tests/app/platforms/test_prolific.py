"""Prolific: the study server's client against the local replica over real HTTP (Prolific's
paths, fields, statuses and refusals), the client's retries and messages, and the dashboard's
review of Prolific participants through the one review interface, with every money action
carried out once even when the server dies between a bonus's set-up and its payment."""

from __future__ import annotations

import os
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from decimal import Decimal
from typing import Any

import httpx
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from server.app.config import StudyConfig
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
from server.app.platforms.review import Reviewed
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import Bonus, Participant
from server.app.storage.replica_models import ProlificReplicaPayment, ProlificReplicaSubmission
from tests.support.server import ADMIN_TOKEN, live

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
    client.pay_bonuses(setup["id"])
    client.pay_bonuses(setup["id"])
    with db.read() as s:
        assert list(s.scalars(select(ProlificReplicaPayment.amount))) == [150, 150]
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
            worker_id=pid,
            assignment_id=submission,
            hit_id=study["id"],
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
    # Killed after the set-up id was stored, as pay was about to be sent, or after it was sent:
    # the outcome is unknown, so pay is never sent again from here (Prolific's pay is not
    # idempotent); the dashboard says to check it on Prolific.
    for token, when in (("tok-before-1", "before"), ("tok-after-1", "after")):
        with pytest.raises(Crash):
            pay(token, "1", when)
        with db.read() as s:
            row = s.scalar(select(Bonus).where(Bonus.unique_token == token))
            assert row is not None and row.state == "paying" and row.setup_id
        with pytest.raises(ApiError, match="will not be paid again") as unknown:
            pay(token, "1")
        assert unknown.value.status == 502
    assert review.reconcile_bonuses(db, backend) == []
    assert payments(db) == [200, 100]  # the one pay that was sent, once


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
