"""Money exactly once: every decision and bonus the platform carried out is in our records and
the export, and none is carried out twice, whatever fails between the platform and us: a
platform that pays and then answers 500 or drops the connection, a duplicate request, two
concurrent requests, and a process killed (SIGKILL) between the call and the record."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
from datetime import timedelta
from decimal import Decimal
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from server.app.errors import ApiError
from server.app.export.tables import export_tables
from server.app.platforms import review
from server.app.platforms.mturk import MTurkClientBackend, MTurkReplicaBackend
from server.app.platforms.review import bonuses, decisions, parse_amount
from server.app.storage.db import Database
from server.app.storage.models import Bonus, Participant, Review, utcnow
from server.app.storage.replica_models import ReplicaAssignment, ReplicaBonus
from tests.support.server import ADMIN_TOKEN, BOUND

ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
BASE = "/api/admin/participants"
ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))


class Crash(BaseException):
    """The server process dying right after the platform answered (nothing after it runs)."""


class ClientError(Exception):
    """botocore's ClientError as the adapter reads it: the error code and message."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(f"An error occurred ({code}): {message}")
        self.response = {"Error": {"Code": code, "Message": message}}


class MTurkStandIn:
    """Mechanical Turk as boto3's client reaches it, with its state: assignments and the bonuses
    paid by UniqueRequestToken ("already exists" for a token it has carried out). ``fault`` says
    what goes wrong after MTurk has done the work: ``500`` (MTurk answers 500, boto3 resends
    with the same token and gets "already exists"), ``drop`` (the connection drops: no answer
    at all), ``crash`` (our process dies before the answer is recorded)."""

    def __init__(self, assignments: dict[str, str]) -> None:
        self.assignments = dict(assignments)  # assignment id -> Submitted, Approved, Rejected
        self.bonuses: dict[str, tuple[str, str]] = {}  # token -> (worker, amount)
        self.faults: list[str] = []
        self.calls: list[str] = []
        self.lock = threading.Lock()

    def _after_work(self) -> None:
        fault = self.faults.pop(0) if self.faults else None
        if fault == "500":  # boto3's retry of the same request
            raise ClientError("RequestError", "The bonus already exists (request id abc-123).")
        if fault == "drop":
            raise ConnectionResetError("Connection was closed before we received a response")
        if fault == "crash":
            raise Crash

    def send_bonus(self, **kw: Any) -> dict[str, Any]:
        with self.lock:
            self.calls.append("send_bonus")
            token = kw["UniqueRequestToken"]
            if token in self.bonuses:
                raise ClientError(
                    "RequestError", f"The bonus for token {token} already exists (request id x)."
                )
            if self.assignments.get(kw["AssignmentId"]) is None:
                raise ClientError("RequestError", "Assignment does not exist.")
            self.bonuses[token] = (kw["WorkerId"], kw["BonusAmount"])
        self._after_work()
        return {}

    def _decide(self, assignment: str, status: str) -> dict[str, Any]:
        with self.lock:
            self.calls.append(status)
            if self.assignments.get(assignment) != "Submitted":
                raise ClientError(
                    "RequestError",
                    "This operation can be called with a status of: Submitted",
                )
            self.assignments[assignment] = status
        self._after_work()
        return {}

    def approve_assignment(self, **kw: Any) -> dict[str, Any]:
        return self._decide(kw["AssignmentId"], "Approved")

    def reject_assignment(self, **kw: Any) -> dict[str, Any]:
        return self._decide(kw["AssignmentId"], "Rejected")

    def get_assignment(self, **kw: Any) -> dict[str, Any]:
        return {"Assignment": {"AssignmentStatus": self.assignments[kw["AssignmentId"]]}}


def submitted(db: Database, worker: str, assignment: str, platform: str = "mturk") -> int:
    """A participant who submitted their work (the rows the study's flow leaves)."""
    with db.write() as s:
        p = Participant(
            token_hash=os.urandom(32).hex(),
            platform=platform,
            platform_participant_id=worker,
            platform_submission_id=assignment,
            platform_study_id="HIT1",
            status="submitted",
        )
        s.add(p)
        s.flush()
        return p.id


def our_bonuses(db: Database) -> list[tuple[str, int, str]]:
    with db.read() as s:
        rows = s.execute(
            select(Bonus.unique_token, Bonus.amount_cents, Bonus.state).order_by(Bonus.id)
        )
        return [tuple(row) for row in rows]  # type: ignore[misc]


@pytest.fixture
def mturk(client: TestClient, db: Database) -> tuple[MTurkStandIn, int]:
    """The dashboard's MTurk backend is the stand-in; one submitted participant."""
    participant = submitted(db, "WORKER1", "ASSIGN1")
    stand_in = MTurkStandIn({"ASSIGN1": "Submitted"})
    client.app.state.server.reviews["mturk"] = MTurkClientBackend(stand_in)  # type: ignore[attr-defined]
    return stand_in, participant


@pytest.mark.parametrize("fault", ["500", "drop", "crash"])
def test_an_mturk_bonus_is_paid_once_and_recorded_whatever_fails_after_paying(
    client: TestClient, db: Database, mturk: tuple[MTurkStandIn, int], fault: str
) -> None:
    stand_in, participant = mturk
    stand_in.faults = [fault]
    bonus = {"amount": "2.00", "reason": "Taught well", "unique_token": "bonus-token-1"}
    backend = client.app.state.server.reviews["mturk"]  # type: ignore[attr-defined]
    if fault == "crash":  # the server process dies inside the request (no answer is sent)
        with pytest.raises(Crash):
            review.pay_bonus(
                db, backend, participant, Decimal("2.00"), "Taught well", "bonus-token-1"
            )
        # The intent was recorded before the call: the money MTurk moved is in our records.
        assert our_bonuses(db) == [("bonus-token-1", 200, "pending")]
    else:
        first = client.post(f"{BASE}/{participant}/bonuses", json=bonus, headers=ADMIN)
        if fault == "500":  # "already exists" for our token means paid
            assert first.status_code == 200, first.text
        else:
            assert first.status_code == 502 and "same token" in first.text, first.text
            assert our_bonuses(db) == [("bonus-token-1", 200, "pending")]
    # The dashboard's retry (same token), twice: no second payment, the bonus is settled.
    for _ in range(2):
        again = client.post(f"{BASE}/{participant}/bonuses", json=bonus, headers=ADMIN)
        assert again.status_code == 200, again.text
        assert [(b["amount"], b["state"]) for b in again.json()["bonuses"]] == [("2.00", "paid")]
    assert stand_in.bonuses == {"bonus-token-1": ("WORKER1", "2.00")}
    assert our_bonuses(db) == [("bonus-token-1", 200, "paid")]
    exported = export_tables(db, pseudonymize=False)["bonuses"]
    assert list(zip(exported["amount"], exported["payment_state"], strict=True)) == [
        ("2.00", "paid")
    ]


@pytest.mark.parametrize("fault", ["500", "drop", "crash"])
def test_an_mturk_decision_taken_then_lost_is_recorded_once(
    client: TestClient, db: Database, mturk: tuple[MTurkStandIn, int], fault: str
) -> None:
    stand_in, participant = mturk
    stand_in.faults = [fault]
    if fault == "crash":  # the server process dies inside the request
        backend = client.app.state.server.reviews["mturk"]  # type: ignore[attr-defined]
        with pytest.raises(Crash):
            review.review_submission(db, backend, participant, "approved", None)
    else:
        first = client.post(f"{BASE}/{participant}/approval", json={}, headers=ADMIN)
        # MTurk's "already approved" on boto3's resend is read back from the assignment.
        assert first.status_code == (200 if fault == "500" else 502), first.text
    again = client.post(f"{BASE}/{participant}/approval", json={}, headers=ADMIN)
    assert again.status_code == 200, again.text
    assert (again.json()["review"]["decision"], again.json()["review"]["state"]) == (
        "approved",
        "done",
    )
    assert stand_in.assignments == {"ASSIGN1": "Approved"}
    # Another decision is refused: a decision is final.
    late = client.post(f"{BASE}/{participant}/rejection", json={"message": "no"}, headers=ADMIN)
    assert late.status_code == 409 and "already approved" in late.text
    with db.read() as s:
        assert list(s.execute(select(Review.decision, Review.state))) == [("approved", "done")]


def test_concurrent_duplicate_bonuses_pay_once_and_both_answer_the_bonus(
    db: Database,
) -> None:
    participant = submitted(db, "WORKER1", "ASSIGN1")
    stand_in = MTurkStandIn({"ASSIGN1": "Submitted"})
    backend = MTurkClientBackend(stand_in)
    start = threading.Barrier(4)
    answers: list[Any] = []

    def pay() -> None:
        start.wait()
        try:
            answers.append(
                review.pay_bonus(db, backend, participant, Decimal("1.25"), "Thanks", "tok-same-1")
            )
        except ApiError as error:  # pragma: no cover - the failure the test is about
            answers.append(error)

    threads = [threading.Thread(target=pay) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=120)
    assert len(answers) == 4 and all(isinstance(a, bool) for a in answers), answers
    assert stand_in.bonuses == {"tok-same-1": ("WORKER1", "1.25")}
    assert our_bonuses(db) == [("tok-same-1", 125, "paid")]


class HeldReplica(MTurkReplicaBackend):
    """The MTurk replica, its answer to the first bonus or approval held until the test lets
    it go."""

    def __init__(self, db: Database) -> None:
        super().__init__(db)
        self.calls = 0
        self.asked = threading.Event()  # the first call is in
        self.answer = threading.Event()  # and may answer

    def _hold(self) -> None:
        self.calls += 1
        if self.calls == 1:
            self.asked.set()
            assert self.answer.wait(BOUND)

    def pay_bonus(self, *args: Any) -> None:
        self._hold()
        super().pay_bonus(*args)

    def approve(self, *args: Any) -> None:
        self._hold()
        super().approve(*args)


@pytest.mark.parametrize("backend", ["postgresql"])
def test_a_bonus_refused_while_its_duplicate_waits_is_refused_to_both(
    db: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two requests for one bonus at once (the same token, on two servers), both finding no
    bonus recorded; the first records its intent, and the platform refuses it (the replica
    has no assignment for the worker) while the second, whose record collided with it, waits
    for the first to settle it. The first takes its intent back, and the second asks again and
    is refused too (it found no bonus once it stopped waiting, and answered 500)."""
    participant = submitted(db, "WORKER1", "NOT-ON-THE-REPLICA")
    backend = HeldReplica(db)
    second_read = threading.Event()  # the second found no bonus recorded
    second_waits = threading.Event()  # its record collided with the first's: it waits

    def check_budget(*args: Any) -> None:
        if threading.current_thread().name == "second":
            second_read.set()
            assert backend.asked.wait(BOUND)  # the first recorded its intent and asks
        budget(*args)

    def wait_for(*args: Any) -> Any:
        second_waits.set()
        return settle(*args)

    budget, settle = bonuses._check_budget, bonuses._wait_for
    monkeypatch.setattr(bonuses, "_check_budget", check_budget)
    monkeypatch.setattr(bonuses, "_wait_for", wait_for)
    answers: dict[str, Any] = {}

    def pay() -> None:
        name = threading.current_thread().name
        try:
            answers[name] = review.pay_bonus(
                db, backend, participant, Decimal("1.25"), "Thanks", "tok-refused-1", 10_000
            )
        except ApiError as error:
            answers[name] = (error.status, error.message)

    second = threading.Thread(target=pay, name="second")
    second.start()
    assert second_read.wait(BOUND)
    first = threading.Thread(target=pay, name="first")
    first.start()
    assert second_waits.wait(BOUND)
    backend.answer.set()
    for thread in (first, second):
        thread.join(timeout=BOUND)
    refusal = (409, "the replica has no assignment NOT-ON-THE-REPLICA")
    assert answers == {"first": refusal, "second": refusal}
    assert backend.calls == 2  # the second asked the platform itself
    assert our_bonuses(db) == []


@pytest.mark.parametrize("backend", ["postgresql"])
def test_an_approval_refused_while_its_duplicate_waits_is_refused_to_both(
    db: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    """As the bonus above, for an approval: the second's record of its intent collides with
    the first's, which the platform refuses and takes back; the second asks again and is
    refused too (it found no decision recorded after the collision, and answered 500)."""
    participant = submitted(db, "WORKER1", "NOT-ON-THE-REPLICA")
    backend = HeldReplica(db)
    second_read = threading.Event()  # the second found no decision recorded
    first_done = threading.Event()
    reads = {"second": 0}

    def now() -> Any:  # stamps the intent, once the transaction found none
        if threading.current_thread().name == "second" and not second_read.is_set():
            second_read.set()
            assert backend.asked.wait(BOUND)  # the first recorded its intent and asks
        return utcnow()

    def read() -> Any:
        if threading.current_thread().name == "second":
            reads["second"] += 1
            if reads["second"] == 2:  # after the collision: the first is refused meanwhile
                backend.answer.set()
                assert first_done.wait(BOUND)
        return database_read()

    database_read = db.read
    monkeypatch.setattr(decisions, "utcnow", now)
    monkeypatch.setattr(db, "read", read)
    answers: dict[str, Any] = {}

    def approve() -> None:
        name = threading.current_thread().name
        try:
            answers[name] = review.review_submission(db, backend, participant, "approved", None)
        except ApiError as error:
            answers[name] = (error.status, error.message)
        finally:
            if name == "first":
                first_done.set()

    second = threading.Thread(target=approve, name="second")
    second.start()
    assert second_read.wait(BOUND)
    first = threading.Thread(target=approve, name="first")
    first.start()
    for thread in (first, second):
        thread.join(timeout=BOUND)
    refusal = (409, "the replica has no assignment NOT-ON-THE-REPLICA")
    assert answers == {"first": refusal, "second": refusal}
    assert backend.calls == 2  # the second asked the platform itself
    with db.read() as s:
        assert s.scalars(select(Review)).all() == []


def test_reconcile_settles_every_unsettled_mturk_bonus_without_paying_again(
    db: Database,
) -> None:
    participant = submitted(db, "WORKER1", "ASSIGN1")
    stand_in = MTurkStandIn({"ASSIGN1": "Submitted"})
    backend = MTurkClientBackend(stand_in)
    stand_in.faults = ["crash"]
    with pytest.raises(Crash):
        review.pay_bonus(db, backend, participant, Decimal("1.00"), "One", "tok-crashed-1")
    stand_in.faults = ["drop"]
    with pytest.raises(ApiError):
        review.pay_bonus(db, backend, participant, Decimal("2.00"), "Two", "tok-dropped-1")
    assert [state for *_, state in our_bonuses(db)] == ["pending", "pending"]
    assert review.reconcile_bonuses(db, backend) == ["tok-crashed-1", "tok-dropped-1"]
    assert our_bonuses(db) == [("tok-crashed-1", 100, "paid"), ("tok-dropped-1", 200, "paid")]
    assert len(stand_in.bonuses) == 2


KILLED_BETWEEN_CALL_AND_RECORD = textwrap.dedent(
    """
    import os, signal, sys
    from decimal import Decimal
    from server.app.storage.db import Database
    from server.app.platforms import review
    from server.app.platforms.mturk import MTurkReplicaBackend

    class DiesAfterPaying(MTurkReplicaBackend):
        def send_bonus(self, *args):
            super().send_bonus(*args)  # the replica's row is committed
            os.kill(os.getpid(), signal.SIGKILL)

    db = Database.from_url(sys.argv[1])
    review.pay_bonus(
        db, DiesAfterPaying(db), int(sys.argv[2]), Decimal("3.00"), "Killed", "tok-killed-1"
    )
    """
)


def test_a_replica_bonus_killed_between_the_call_and_the_record_is_settled_once(
    client: TestClient, db: Database
) -> None:
    participant = submitted(db, "WORKER1", "ASSIGN1")
    with db.write() as s:
        s.add(
            ReplicaAssignment(
                hit_id="HIT1", assignment_id="ASSIGN1", worker_id="WORKER1", status="submitted"
            )
        )
    url = db.engine.url.render_as_string(hide_password=False)
    killed = subprocess.run(
        [sys.executable, "-c", KILLED_BETWEEN_CALL_AND_RECORD, url, str(participant)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    assert our_bonuses(db) == [("tok-killed-1", 300, "pending")]
    bonus = {"amount": "3.00", "reason": "Killed", "unique_token": "tok-killed-1"}
    retried = client.post(f"{BASE}/{participant}/bonuses", json=bonus, headers=ADMIN)
    assert retried.status_code == 200, retried.text
    with db.read() as s:
        assert list(s.scalars(select(ReplicaBonus.unique_request_token))) == ["tok-killed-1"]
    assert our_bonuses(db) == [("tok-killed-1", 300, "paid")]
    assert list(export_tables(db)["bonuses"]["unique_token"]) == ["tok-killed-1"]
    assert isinstance(MTurkReplicaBackend(db), MTurkReplicaBackend)


@pytest.mark.parametrize(
    "amount",
    [
        "1_0",
        "١٠",
        "１０",
        "1e1",
        "1.234",
        " 1.00",
        "1.",
        ".5",
        "+1",
        "-1",
        "0",
        "0.00",
        "100.01",
        "NaN",
        "Infinity",
        True,
        None,
        [],
        1e-7,
    ],
)
def test_amounts_that_are_not_plain_ascii_decimals_are_refused(amount: Any) -> None:
    with pytest.raises(ValueError):
        parse_amount(amount)


def test_plain_amounts_are_taken_exactly() -> None:
    assert [parse_amount(v) for v in ("1.50", "0.01", "100", 5, 0.25, "12.5")] == [
        Decimal("1.50"),
        Decimal("0.01"),
        Decimal("100"),
        Decimal("5"),
        Decimal("0.25"),
        Decimal("12.5"),
    ]


def test_bad_amounts_and_texts_are_refused_by_the_dashboard_and_store_nothing(
    client: TestClient, db: Database
) -> None:
    participant = submitted(db, "WORKER1", "ASSIGN1")
    good = {"amount": "1.00", "reason": "Thanks", "unique_token": "tok-refused-1"}
    for change in (
        {"amount": "1_0"},
        {"amount": "١٠"},
        {"amount": "１０"},
        {"reason": "   "},
        {"reason": "bell\x07"},
        {"reason": "escape\x1b[31m"},
    ):
        answer = client.post(
            f"{BASE}/{participant}/bonuses", json={**good, **change}, headers=ADMIN
        )
        assert answer.status_code == 422, (change, answer.text)
        assert next(iter(change)) in answer.text
    for feedback in ("  ", "tab\tis fine but not \x00", "nul\x1f"):
        answer = client.post(
            f"{BASE}/{participant}/rejection", json={"message": feedback}, headers=ADMIN
        )
        assert answer.status_code == 422 and "message" in answer.text, answer.text
    assert our_bonuses(db) == []
    with db.read() as s:
        assert s.scalar(select(Review)) is None


def test_the_reconciliation_endpoint_settles_a_dropped_bonus_once(
    client: TestClient, db: Database, mturk: tuple[MTurkStandIn, int]
) -> None:
    stand_in, participant = mturk
    stand_in.faults = ["drop"]
    bonus = {"amount": "4.00", "reason": "Kept going", "unique_token": "tok-reconcile-1"}
    lost = client.post(f"{BASE}/{participant}/bonuses", json=bonus, headers=ADMIN)
    assert lost.status_code == 502
    assert client.post("/api/admin/reconciliation").status_code == 401
    settled = client.post("/api/admin/reconciliation", headers=ADMIN)
    assert settled.status_code == 200, settled.text
    assert settled.json() == {"settled_bonuses": ["tok-reconcile-1"], "prolific_statuses": {}}
    again = client.post("/api/admin/reconciliation", headers=ADMIN)
    assert again.json()["settled_bonuses"] == []
    assert stand_in.bonuses == {"tok-reconcile-1": ("WORKER1", "4.00")}
    assert our_bonuses(db) == [("tok-reconcile-1", 400, "paid")]


def test_an_mturk_bonus_older_than_mturks_token_memory_is_never_sent_again(
    db: Database,
) -> None:
    """MTurk forgets a UniqueRequestToken after 24 hours: a bonus paid whose answer was lost,
    found unsettled a day later, is marked in doubt and never sent again (sent again, a
    forgetful MTurk would pay it twice)."""
    participant = submitted(db, "WORKER1", "ASSIGN1")
    stand_in = MTurkStandIn({"ASSIGN1": "Submitted"})
    backend = MTurkClientBackend(stand_in)
    stand_in.faults = ["drop"]  # paid, and the answer lost
    with pytest.raises(ApiError):
        review.pay_bonus(db, backend, participant, Decimal("1.00"), "Thanks", "tok-old-1")
    assert our_bonuses(db) == [("tok-old-1", 100, "pending")]
    with db.write() as s:  # 25 hours later, MTurk has forgotten the token
        bonus = s.scalar(select(Bonus))
        assert bonus is not None
        bonus.requested_at -= timedelta(hours=25)
    stand_in.bonuses.clear()
    assert review.reconcile_bonuses(db, backend) == []
    with pytest.raises(ApiError) as doubt:
        review.pay_bonus(db, backend, participant, Decimal("1.00"), "Thanks", "tok-old-1")
    assert doubt.value.status == 409 and "in doubt" in doubt.value.message
    assert stand_in.calls.count("send_bonus") == 1  # paid once, never sent again
    assert our_bonuses(db) == [("tok-old-1", 100, "in_doubt")]
    # One a few hours old is still settled by its token, as before.
    stand_in.faults = ["drop"]
    with pytest.raises(ApiError):
        review.pay_bonus(db, backend, participant, Decimal("2.00"), "More", "tok-new-1")
    assert review.reconcile_bonuses(db, backend) == ["tok-new-1"]
    assert stand_in.calls.count("send_bonus") == 3 and len(stand_in.bonuses) == 1
