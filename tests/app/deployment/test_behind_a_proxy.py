"""The deployment as it runs: three ``serve`` processes on one PostgreSQL database behind
Debian's nginx (a process of the test's own, on loopback ports, with its own configuration and
prefix), simulated participants through the proxy, one server killed with SIGKILL in the
middle. Nothing acknowledged is lost, no update's result is stored twice and an update runs
again only where the killed server's claim had it, every update is done once the survivors
take over, no place in the study is given twice (more participants arrive at once than it has
places, on different servers), each bonus is paid once at the platform (the servers' own MTurk
replica) however many servers it is asked of and whichever dies, no server answers 500, the
dashboard signed in once works on every server, and the sign-in limit counts across them."""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pytest
from sqlalchemy import func, select

from server.app.admin_auth import FAILURES_ALLOWED
from server.app.storage.db import Database
from server.app.storage.models import (
    Bonus,
    Event,
    LearnerUpdate,
    LearningSession,
    Participant,
    StatusChange,
    StudyServer,
)
from server.app.storage.replica_models import ReplicaAssignment, ReplicaBonus
from server.app.storage.vocabulary import IN_PROGRESS, ParticipantStatus
from server.commands.live import Proxy, ServerProcess
from server.commands.simulated import MTurkReplicaArrival, TeachingPlan, run_participants
from tests.app.test_live import fast_study_file
from tests.support.server import ADMIN_TOKEN, BOUND, count_events, wait_for_updates

ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
LEASE_SECONDS = 3  # the killed server's claims are taken over this long after its death
PARTICIPANTS = 6
PLACES = 4  # participants in the study at once (its study file's max_active_participants)
BONUS = {"amount": "0.75", "reason": "Thank you for teaching every agent."}


@pytest.fixture
def servers(db: Database, tmp_path: Path) -> Iterator[list[ServerProcess]]:
    study = fast_study_file(tmp_path)
    study.write_text(f"max_active_participants = {PLACES}\n" + study.read_text())
    environment = {
        "BAM_DATABASE_URL": db.engine.url.render_as_string(hide_password=False),
        "BAM_ADMIN_TOKEN": ADMIN_TOKEN,
        "BAM_STUDY_CONFIG": str(study),
        "BAM_UPDATE_WORKERS": "1",
        "BAM_UPDATE_LEASE_SECONDS": str(LEASE_SECONDS),
        # The proxy's X-Forwarded-For names the participant's address (the sign-in limit's).
        "BAM_FORWARDED_ALLOW_IPS": "127.0.0.1",
    }
    started: list[ServerProcess] = []
    try:
        for number in range(3):
            folder = tmp_path / f"server-{number}"
            folder.mkdir()
            server = ServerProcess(folder, environment, access_log=True)
            server.start()
            started.append(server)
        yield started
    finally:
        for server in started:
            server.stop()


@pytest.fixture
def proxy(servers: list[ServerProcess], tmp_path: Path) -> Iterator[str]:
    upstreams = [f"127.0.0.1:{server.port}" for server in servers]
    with Proxy(tmp_path / "nginx", upstreams) as nginx:
        yield nginx.url


def sign_in(url: str) -> str:
    answer = httpx.post(
        f"{url}/dashboard/login", data={"token": ADMIN_TOKEN, "next": "/dashboard"}, timeout=BOUND
    )
    assert answer.status_code == 303, answer.text
    cookie = answer.cookies.get("bam_admin")
    assert cookie is not None
    return cookie


class BonusPayer:
    """The experimenter paying each participant who submitted a bonus, from the dashboard,
    while the study runs: each bonus asked of two servers at once (one token a participant, as
    a form sent twice), the servers taken in turn, the proxy among them, until ``ENOUGH``
    answers said it paid. A server that is down, or nginx's 502 for a request it lost, is
    asked again; every other answer is kept for the test."""

    ENOUGH = 3

    def __init__(self, db: Database, urls: list[str]) -> None:
        self.db = db
        self.urls = urls
        self.answers: Counter[int] = Counter()
        self.answered_by: Counter[str] = Counter()  # url -> answers
        self.said_paid: Counter[int] = Counter()  # participant -> answers saying paid
        self.refused: list[str] = []  # answers neither 200 nor a lost request
        self.stop = threading.Event()
        self.turn = 0

    def submitted(self) -> list[int]:
        with self.db.read() as s:
            found = s.scalars(
                select(Participant.id).where(Participant.status == ParticipantStatus.SUBMITTED)
            )
            return list(found)

    def ask(self, url: str, participant: int) -> bool:
        """Whether ``url`` answered that the bonus is paid."""
        body = {**BONUS, "unique_token": f"bonus-for-{participant}"}
        try:
            answer = httpx.post(
                f"{url}/api/admin/participants/{participant}/bonuses",
                json=body,
                headers=ADMIN,
                timeout=BOUND,
            )
        except httpx.TransportError:
            return False  # that server is down
        self.answers[answer.status_code] += 1
        self.answered_by[url] += 1
        if answer.status_code == 200:
            return [b["state"] for b in answer.json()["bonuses"]] == ["paid"]
        if answer.status_code != 502 or url != self.urls[0]:
            self.refused.append(f"{url}: {answer.status_code} {answer.text[:300]}")
        return False

    def round(self, pool: ThreadPoolExecutor) -> set[int]:
        """Each submitted participant's bonus asked of the next two servers at once; the
        participants whose bonus an answer said paid."""
        asked = []
        for participant in self.submitted():
            if self.said_paid[participant] >= self.ENOUGH:
                continue
            targets = [self.urls[(self.turn + k) % len(self.urls)] for k in range(2)]
            self.turn += 1
            asked += [(participant, pool.submit(self.ask, url, participant)) for url in targets]
        for participant, paid in asked:
            self.said_paid[participant] += paid.result()
        return {participant for participant, count in self.said_paid.items() if count}

    def run(self) -> None:
        with ThreadPoolExecutor(2) as pool:
            while not self.stop.is_set():
                self.round(pool)
                time.sleep(0.5)

    def settle(self, participants: int, timeout: float = 120.0) -> None:
        """After the study: ask until every participant's bonus was said paid."""
        deadline = time.monotonic() + timeout
        with ThreadPoolExecutor(2) as pool:
            while len(self.round(pool)) < participants:
                assert time.monotonic() < deadline, self.answers
                time.sleep(0.5)


def most_at_once_in_the_study(db: Database) -> tuple[int, dict[int, list[str]]]:
    """The most participants in the study at once, replayed from the status changes in the
    order they were written (an admission counts its place under a lock, after the changes
    that freed it were committed), and each participant's statuses in order."""
    with db.read() as s:
        changes = s.execute(
            select(StatusChange.participant_id, StatusChange.status).order_by(StatusChange.id)
        ).all()
    flow = {status.value for status in ParticipantStatus}  # not the exclusion marks
    statuses: dict[int, list[str]] = {}
    inside: set[int] = set()
    most = 0
    for participant, status in changes:
        statuses.setdefault(participant, []).append(status)
        if status in IN_PROGRESS:
            inside.add(participant)
        elif status in flow:
            inside.discard(participant)
        most = max(most, len(inside))
    return most, statuses


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["postgresql"])
def test_three_servers_behind_nginx_lose_nothing_when_one_is_killed(
    db: Database, servers: list[ServerProcess], proxy: str
) -> None:
    # Signed in once, through the proxy: the cookie works on every server.
    cookie = sign_in(proxy)
    for server in servers:
        answer = httpx.get(f"{server.url}/api/admin/participants", cookies={"bam_admin": cookie})
        assert answer.status_code == 200, answer.text

    plan = TeachingPlan(min_rounds=1, max_rounds=2, agent_try_probability=0.5, max_agent_steps=8)
    result: dict[str, object] = {}

    def study() -> None:
        result["run"] = run_participants(
            proxy,
            participants=PARTICIPANTS,
            concurrency=PARTICIPANTS,
            seed=5,
            plan=plan,
            mturk_replica=MTurkReplicaArrival(ADMIN_TOKEN),
        )

    thread = threading.Thread(target=study)
    thread.start()
    payer = BonusPayer(db, [proxy] + [server.url for server in servers])
    paying = threading.Thread(target=payer.run)
    paying.start()
    # Kill the second server in the middle of teaching, once it has been paying bonuses: its
    # claims on updates die with it, and whatever bonus it was paying.
    killed = servers[1]
    while (count_events(db) < 600 or not payer.answered_by[killed.url]) and thread.is_alive():
        time.sleep(0.05)
    assert thread.is_alive(), "the study ended before the kill"
    assert killed.process is not None
    killed_pid = killed.process.pid
    killed.kill()
    thread.join(timeout=900)
    assert not thread.is_alive()
    payer.stop.set()
    paying.join(timeout=BOUND)
    run = result["run"]
    assert [p.error for p in run.participants] == [None] * PARTICIPANTS  # type: ignore[attr-defined]
    assert run.completed == PARTICIPANTS  # type: ignore[attr-defined]
    # Every acknowledged request is stored once: no gaps, no duplicates.
    assert run.acknowledged == count_events(db)  # type: ignore[attr-defined]
    wait_for_updates(db, timeout=300)
    with db.read() as s:
        seqs = s.execute(
            select(Event.participant_id, func.count(), func.max(Event.seq)).group_by(
                Event.participant_id
            )
        ).all()
        names = {row.pid: row.name for row in s.scalars(select(StudyServer))}
        updates = list(s.scalars(select(LearnerUpdate)))
        sessions = list(s.scalars(select(LearningSession)))
    assert all(count == highest for _, count, highest in seqs)
    # Every update done once the survivors took over; each in order, one per episode.
    assert all(update.status == "done" for update in updates)
    for session in sessions:
        indices = sorted(u.update_index for u in updates if u.session_id == session.id)
        assert indices == list(range(session.episodes + 1))
    # No update ran twice: one run each, but where the killed server's claim had it (its
    # lease expired, a survivor took it over and stored the one result).
    dead = names[killed_pid]
    for update in updates:
        assert update.runs == 1 or (update.runs == 2 and update.taken_from == dead), (
            update.id,
            update.runs,
            update.taken_from,
        )
        assert update.claimed_by != dead or update.runs == 1
    assert len({update.claimed_by for update in updates}) >= 2  # the servers shared them

    # No place given twice: all arrived at once, on different servers, beyond the places;
    # never more in the study than it has places, and each went in once.
    most, statuses = most_at_once_in_the_study(db)
    assert most == PLACES, statuses
    assert any(ParticipantStatus.WAITING in history for history in statuses.values())
    assert len(statuses) == PARTICIPANTS
    for history in statuses.values():
        assert history.count(ParticipantStatus.ARRIVED) == 1, history
        assert history[-1] == ParticipantStatus.SUBMITTED, history
    # Each worker had an assignment of their own on the replica, and submitted it there.
    with db.read() as s:
        assignments = list(s.scalars(select(ReplicaAssignment)))
    assert len({a.assignment_id for a in assignments}) == len(assignments) == PARTICIPANTS
    assert {a.status for a in assignments} == {"submitted"}

    # Every bonus paid once at the platform, however many servers were asked, one died.
    payer.settle(PARTICIPANTS)
    with db.read() as s:
        paid = s.execute(select(ReplicaBonus.unique_request_token, ReplicaBonus.amount)).all()
        ours = s.execute(select(Bonus.unique_token, Bonus.state, Bonus.amount_cents)).all()
    tokens = {f"bonus-for-{participant}" for participant in statuses}
    assert sorted(token for token, _ in paid) == sorted(tokens)
    assert {amount for _, amount in paid} == {BONUS["amount"]}
    assert sorted(ours) == sorted((token, "paid", 75) for token in tokens)
    assert payer.refused == [] and payer.answers[200] > 2 * PARTICIPANTS, payer.answers

    survivors = [servers[0], servers[2]]
    # The cookie still works on the survivors and through the proxy.
    for url in [server.url for server in survivors] + [proxy]:
        answer = httpx.get(f"{url}/api/admin/participants", cookies={"bam_admin": cookie})
        assert answer.status_code == 200, answer.text
    # The sign-in limit counts across the servers: wrong tokens spread over them, then 429.
    for attempt in range(FAILURES_ALLOWED):
        url = survivors[attempt % 2].url
        wrong = httpx.post(f"{url}/dashboard/login", data={"token": "guess"}, timeout=BOUND)
        assert wrong.status_code == 401, wrong.text
    for url in [server.url for server in survivors] + [proxy]:
        refused = httpx.get(f"{url}/api/admin/participants", headers=ADMIN, timeout=BOUND)
        assert refused.status_code == 429, refused.text
    # No server answered 500, whatever the participants' retries hid.
    assert {server.url: server.answers(500) for server in servers} == {
        server.url: [] for server in servers
    }
