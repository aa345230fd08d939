"""The deployment as it runs: three ``serve`` processes on one PostgreSQL database behind
Debian's nginx (a process of the test's own, on loopback ports, with its own configuration and
prefix), simulated participants through the proxy, one server killed with SIGKILL in the
middle. Nothing acknowledged is lost, no update's result is stored twice and an update runs
again only where the killed server's claim had it, every update is done once the survivors
take over, the dashboard signed in once works on every server, and the sign-in limit counts
across them."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from sqlalchemy import func, select

from server.app.admin_auth import FAILURES_ALLOWED
from server.app.storage.db import Database
from server.app.storage.models import Event, LearnerUpdate, LearningSession, StudyServer
from server.commands.live import Proxy, ServerProcess
from server.commands.simulated import TeachingPlan, run_participants
from tests.app.test_live import fast_study_file
from tests.support.server import ADMIN_TOKEN, BOUND, count_events, wait_for_updates

ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
LEASE_SECONDS = 3  # the killed server's claims are taken over this long after its death


@pytest.fixture
def servers(db: Database, tmp_path: Path) -> Iterator[list[ServerProcess]]:
    study = fast_study_file(tmp_path)
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
            server = ServerProcess(folder, environment)
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
        result["run"] = run_participants(proxy, participants=6, concurrency=6, seed=5, plan=plan)

    thread = threading.Thread(target=study)
    thread.start()
    # Kill the second server in the middle of teaching: its claims on updates die with it.
    killed = servers[1]
    while count_events(db) < 600 and thread.is_alive():
        time.sleep(0.05)
    assert thread.is_alive(), "the study ended before the kill"
    assert killed.process is not None
    killed_pid = killed.process.pid
    killed.kill()
    thread.join(timeout=900)
    assert not thread.is_alive()
    run = result["run"]
    assert [p.error for p in run.participants] == [None] * 6  # type: ignore[attr-defined]
    assert run.completed == 6  # type: ignore[attr-defined]
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
