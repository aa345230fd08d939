"""A whole paid study rehearsed on the local Prolific replica, over real HTTP: the study made
and published through the Prolific client, twelve participants of whom one returns, one times
out and one declines consent (and returns the submission Prolific then asks them to
return); their places refilled and the balanced assignment blind to them; nine approved in
bulk but one rejected with a category, three bonuses, one with a crash between its set-up and
its payment, one whose pay answers 429 after paying (in doubt, then settled from the
submission's bonus_payments): the replica records every decision and exactly one payment per
bonus, and the export says the same."""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from decimal import Decimal
from typing import Any

import httpx
import pytest
from sqlalchemy import select

from server.app.export.tables import export_tables
from server.app.main import create_app
from server.app.platforms import review
from server.app.platforms.prolific import ProlificBackend, ProlificClient
from server.app.platforms.prolific_replica import ReplicaTransport
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import Participant as ParticipantRow
from server.app.storage.replica_models import ProlificReplicaPayment, ProlificReplicaSubmission
from server.app.study_file import StudyConfig
from tests.app.platforms.test_prolific import (
    REASON,
    Crash,
    CrashesAroundPay,
    FailingPay,
    draft,
)

# The replica's webhooks are signed with the server's secret, as Prolific's are.
from tests.app.platforms.test_prolific_sync import settings as settings
from tests.support.server import (
    ADMIN_TOKEN,
    Participant,
    demonstrate_each_task,
    live,
    study_config,
    wait_until,
)

ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
DOMAINS = ("navigation", "farming", "gravity")
PLACES = 9


def prolific_study(**extra: Any) -> StudyConfig:
    """Three domains of one environment and one agent each, no tutorial, on Prolific; ``extra``:
    more of the study file's keys."""
    return study_config(
        learners=["cloning"],
        domains=[
            {"name": "navigation", "environments": ["wall"]},
            {"name": "farming", "environments": ["two-fields"]},
            {"name": "gravity", "environments": ["flip"]},
        ],
        tutorial={"enabled": False},
        questionnaire={"questions": []},
        completion={
            "mode": "prolific",
            "prolific_code": "C1A2B3C4",
            "prolific_no_consent_code": "NOCONSNT",
        },
        **extra,
    )


@pytest.fixture
def study() -> StudyConfig:
    return prolific_study()


@pytest.fixture
def server(
    db: Database, settings: Settings, study: StudyConfig, executor: ProcessPoolExecutor
) -> Iterator[tuple[str, Any]]:
    app = create_app(settings, study, db=db, executor=executor)
    with live(app) as base:
        yield base, app


class Person:
    """One Prolific participant with a browser of their own: takes a place on the replica, is
    sent to the study with the placeholders filled, and ends where the page sends them."""

    def __init__(self, base: str, study_id: str) -> None:
        self.browser = httpx.Client(base_url=base, headers=ADMIN, timeout=120)
        sent = self.browser.post(f"/prolific/studies/{study_id}/take-part")
        assert sent.status_code == 303, sent.text
        link = httpx.URL(sent.headers["location"])
        assert link.path == "/study", link
        self.link = {key: link.params[key] for key in ("PROLIFIC_PID", "STUDY_ID", "SESSION_ID")}
        arrived = self.browser.post("/api/arrivals", json=self.link)
        assert arrived.status_code == 201, arrived.text
        self.api = Participant(self.browser, arrived.json()["token"])
        self.submission = self.link["SESSION_ID"]

    @property
    def id(self) -> int:
        return int(self.api.get("/api/participant")["participant_id"])

    def consent(self, agree: bool = True) -> dict[str, Any]:
        return self.api.act("/api/participant/consent", agree=agree)["participant"]

    def teach_and_submit(self) -> None:
        session = self.api.act("/api/participant/start")["participant"]["current_session_id"]
        demonstrate_each_task(self.api, session)
        done = self.api.act(f"/api/sessions/{session}/finish")["participant"]
        assert done["status"] == "completed", done
        self.api.act("/api/participant/submission")
        self.leave(done["completion"])

    def leave(self, completion: dict[str, Any]) -> None:
        """Where the page sends them at the end: for a study of the replica, the replica's
        completion URL (on Prolific, the study's prolific_url)."""
        code = completion["code"]
        assert completion["redirect_url"] == f"/prolific/submissions/complete?cc={code}"
        landed = self.browser.get(completion["redirect_url"])
        assert landed.status_code == 200 and f"Completion code {code} accepted" in landed.text

    def end(self, how: str) -> None:
        """``return`` or ``time-out``, as the participant or Prolific ends the submission."""
        ended = self.browser.post(f"/prolific/submissions/{self.submission}/{how}")
        assert ended.status_code == 303, ended.text


def replica_statuses(db: Database) -> dict[str, str]:
    with db.read() as s:
        return {r.id: r.status for r in s.scalars(select(ProlificReplicaSubmission))}


def ours(db: Database) -> dict[int, tuple[str, str | None, str | None]]:
    """Participant -> (status, Prolific status, domain)."""
    with db.read() as s:
        return {
            p.id: (p.status, p.platform_status, p.domain) for p in s.scalars(select(ParticipantRow))
        }


def test_a_paid_study_rehearsed_on_the_replica(server: tuple[str, Any], db: Database) -> None:
    base, app = server
    client = ProlificClient(f"{base}/prolific/api/v1", ADMIN_TOKEN, first_wait=0.01)
    made = draft(places=PLACES)
    made["external_study_url"] = (
        f"{base}/study?PROLIFIC_PID={{{{%PROLIFIC_PID%}}}}&STUDY_ID={{{{%STUDY_ID%}}}}"
        "&SESSION_ID={{%SESSION_ID%}}"
    )
    study = client.create_study(made)
    assert client.transition_study(study["id"], "PUBLISH")["status"] == "ACTIVE"

    # Three leave without completing. One declines consent: sent back with the NO_CONSENT
    # code, which completes the replica's submission and asks them to return it (as Prolific:
    # it holds its place until they do); they return it.
    decliner = Person(base, study["id"])
    declined = decliner.consent(agree=False)
    assert declined["status"] == "declined" and declined["completion"]["code"] == "NOCONSNT"
    decliner.leave(declined["completion"])
    assert replica_statuses(db)[decliner.submission] == "AWAITING REVIEW"
    wait_until(
        lambda: ours(db)[decliner.id][:2] == ("declined", "AWAITING REVIEW"),
        "the server recorded the decliner's completed submission",
    )
    decliner.end("return")
    assert replica_statuses(db)[decliner.submission] == "RETURNED"
    wait_until(
        lambda: ours(db)[decliner.id][:2] == ("declined", "RETURNED"),
        "the server recorded the decliner's return",
    )

    def domain(person: Person) -> str | None:
        return ours(db)[person.id][2]

    # One returns the study and one's time runs out, each while two others are in the study
    # in the two other domains: released at once (the replica's signed webhook), they hold no
    # domain any more, so the next participant is given theirs.
    completers: list[Person] = []
    for how, status in (("return", "RETURNED"), ("time-out", "TIMED-OUT")):
        dropout = Person(base, study["id"])
        dropout.consent()
        dropout.api.act("/api/participant/start")
        others = [Person(base, study["id"]) for _ in range(2)]
        for person in others:
            person.consent()
        assert {domain(dropout), *map(domain, others)} == set(DOMAINS), ours(db)
        dropout.end(how)
        wait_until(
            lambda d=dropout, st=status: ours(db)[d.id][:2] == ("returned", st),
            f"the server released the participant whose submission is {status}",
        )
        after = Person(base, study["id"])
        after.consent()
        assert domain(after) == domain(dropout), ours(db)
        completers += [*others, after]

    # Three more fill the last places (the three freed places refilled); all nine complete.
    for _ in range(3):
        person = Person(base, study["id"])
        person.consent()
        completers.append(person)
    for person in completers:
        person.teach_and_submit()
    assert client.get_study(study["id"])["status"] == "AWAITING REVIEW"  # every place taken
    statuses = replica_statuses(db)
    assert len(statuses) == 12
    assert Counter(statuses.values()) == {"AWAITING REVIEW": 9, "RETURNED": 2, "TIMED-OUT": 1}
    # Balanced over the nine who hold a place: the three who left count nowhere.
    assert Counter(map(domain, completers)) == dict.fromkeys(DOMAINS, 3)

    # Review: one rejected with a category; all nine asked in bulk, the rejected one refused.
    rejected, *approved = (p.id for p in completers)
    answer = httpx.post(
        f"{base}/api/admin/participants/{rejected}/rejection",
        json={"message": REASON, "rejection_category": "NO_DATA"},
        headers=ADMIN,
    )
    assert answer.status_code == 200, answer.text
    bulk = httpx.post(
        f"{base}/api/admin/approvals",
        json={"participant_ids": [p.id for p in completers]},
        headers=ADMIN,
        timeout=120,
    )
    assert bulk.status_code == 200, bulk.text
    assert sorted(bulk.json()["approved"]) == sorted(approved)
    assert "already rejected" in bulk.json()["refused"][str(rejected)]

    # Two bonuses; the first crashes between Prolific's set-up and its pay, then is retried
    # from the dashboard with the same token: the replica pays each once.
    backend = app.state.server.review_backend("prolific")
    first, second = approved[:2]
    with pytest.raises(Crash):
        review.pay_bonus(
            db,
            CrashesAroundPay(backend, "set-up"),
            first,
            Decimal("1.25"),
            "Thanks",
            "bonus-token-1",
        )
    for who, amount, token in ((first, "1.25", "bonus-token-1"), (second, "0.50", "bonus-token-2")):
        for _ in range(2):  # a double click answers the same and pays nothing more
            paid = httpx.post(
                f"{base}/api/admin/participants/{who}/bonuses",
                json={"amount": amount, "reason": "Thanks", "unique_token": token},
                headers=ADMIN,
            )
            assert paid.status_code == 200, paid.text
    # A third: Prolific's pay answers 429 after paying. The bonus is in doubt, and the resend
    # settles it from the submission's bonus_payments without paying it again.
    third = approved[2]
    app.state.server.reviews["prolific"] = ProlificBackend(
        ProlificClient(
            "http://replica/prolific/api/v1",
            ADMIN_TOKEN,
            transport=FailingPay(ReplicaTransport(db, ADMIN_TOKEN), "paid-429"),
        ),
        "GBP",
        name="prolific-replica",
    )
    bonus = {"amount": "0.75", "reason": "Thanks", "unique_token": "bonus-token-3"}
    doubt = httpx.post(f"{base}/api/admin/participants/{third}/bonuses", json=bonus, headers=ADMIN)
    assert doubt.status_code == 502 and "is in doubt" in doubt.text
    shown = httpx.get(f"{base}/api/admin/participants/{third}", headers=ADMIN).json()
    assert [b["state"] for b in shown["bonuses"]] == ["in_doubt"]
    app.state.server.reviews["prolific"] = backend
    for _ in range(2):
        settled = httpx.post(
            f"{base}/api/admin/participants/{third}/bonuses", json=bonus, headers=ADMIN
        )
        assert settled.status_code == 200, settled.text
        assert [b["state"] for b in settled.json()["bonuses"]] == ["paid"]
    pids = {p.id: p.link["PROLIFIC_PID"] for p in completers}
    with db.read() as s:
        payments = sorted(
            (row.participant_id, row.amount) for row in s.scalars(select(ProlificReplicaPayment))
        )
    assert payments == sorted([(pids[first], 125), (pids[second], 50), (pids[third], 75)])

    statuses = replica_statuses(db)
    assert statuses[completers[0].submission] == "REJECTED"
    assert all(statuses[p.submission] == "APPROVED" for p in completers[1:])

    # The export holds the same: reviews, bonuses and each participant's Prolific status.
    tables = export_tables(db)
    reviews = tables["reviews"]
    assert Counter(reviews["decision"]) == {"approved": 8, "rejected": 1}
    assert set(reviews.loc[reviews["decision"] == "rejected", "rejection_category"]) == {"NO_DATA"}
    bonuses = tables["bonuses"]
    assert sorted(bonuses["amount"].astype(str)) == ["0.50", "0.75", "1.25"]
    assert set(bonuses["payment_state"]) == {"paid"}
    participants = tables["participants"]
    assert Counter(participants["prolific_status"]) == {
        "APPROVED": 8,
        "REJECTED": 1,
        "RETURNED": 2,  # the one who returned, and the one who declined consent
        "TIMED-OUT": 1,
    }
    client.close()
