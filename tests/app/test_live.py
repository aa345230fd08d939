"""A live server process: simulated participants over HTTP while the server is killed and
restarted mid-study; they finish and nothing is lost (events acknowledged == events stored)."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from sqlalchemy import func, select

from server.app.storage.db import Database
from server.app.storage.models import Event, LearnerUpdate, LearningSession
from server.app.study_file import DEFAULT_STUDY_CONFIG
from server.commands.live import ServerProcess
from server.commands.simulated import TeachingPlan, run_participants
from tests.support.server import ADMIN_TOKEN, FAST_LEARNERS, count_events, wait_for_updates


def fast_study_file(folder: Path) -> Path:
    """The paper's study with the fast learner settings, as a file for the server process."""
    lines = [DEFAULT_STUDY_CONFIG.read_text()]
    for learner, settings in FAST_LEARNERS.items():
        lines.append(f'\n[learner_settings."{learner}"]')
        lines += [f"{key} = {value}" for key, value in settings.items()]
    path = folder / "study.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture
def live(db: Database, tmp_path: Path) -> Iterator[ServerProcess]:
    environment = {
        "BAM_DATABASE_URL": db.engine.url.render_as_string(hide_password=False),
        "BAM_ADMIN_TOKEN": ADMIN_TOKEN,
        "BAM_STUDY_CONFIG": str(fast_study_file(tmp_path)),
        "BAM_UPDATE_WORKERS": "2",
    }
    with ServerProcess(tmp_path, environment) as server:
        yield server


@pytest.mark.slow
def test_a_study_survives_a_server_crash_with_nothing_lost(
    live: ServerProcess, db: Database
) -> None:
    plan = TeachingPlan(min_rounds=1, max_rounds=2, agent_try_probability=0.5, max_agent_steps=10)
    result: dict[str, object] = {}

    def study() -> None:
        result["run"] = run_participants(live.url, participants=4, concurrency=4, seed=3, plan=plan)

    thread = threading.Thread(target=study)
    thread.start()
    # Crash the server twice while participants are in the middle of teaching.
    for threshold in (400, 1800):
        while count_events(db) < threshold and thread.is_alive():
            time.sleep(0.05)
        assert thread.is_alive(), "the study ended before the crash"
        live.kill()
        time.sleep(1.0)
        live.start()
    thread.join(timeout=600)
    assert not thread.is_alive()
    run = result["run"]
    assert [p.error for p in run.participants] == [None] * 4  # type: ignore[attr-defined]
    assert run.completed == 4  # type: ignore[attr-defined]
    assert run.acknowledged == count_events(db)  # type: ignore[attr-defined]
    assert sum(p.retries for p in run.participants) > 0  # type: ignore[attr-defined]
    wait_for_updates(db, timeout=300)
    with db.read() as s:
        sessions = s.scalars(select(LearningSession)).all()
        assert all(x.status == "finished" and x.completed for x in sessions)
        for session in sessions:
            indices = s.scalars(
                select(LearnerUpdate.update_index)
                .where(LearnerUpdate.session_id == session.id)
                .order_by(LearnerUpdate.update_index)
            ).all()
            assert list(indices) == list(range(session.episodes + 1))
        assert (
            s.scalar(
                select(func.count())
                .select_from(LearnerUpdate)
                .where(LearnerUpdate.status != "done")
            )
            == 0
        )
        seqs = s.execute(
            select(Event.participant_id, func.count(), func.max(Event.seq)).group_by(
                Event.participant_id
            )
        ).all()
    assert all(count == highest for _, count, highest in seqs)  # no gaps, no duplicates
    # The export of the live server has every participant.
    response = httpx.get(
        f"{live.url}/api/admin/participants", headers={"Authorization": f"Bearer {ADMIN_TOKEN}"}
    )
    assert [p["status"] for p in response.json()] == ["submitted"] * 4


@pytest.mark.slow
def test_the_teach_command_against_a_live_server(live: ServerProcess, db: Database) -> None:
    completed = subprocess.run(
        [
            sys.executable,
            "-m",
            "server.commands.main",
            "teach",
            "--url",
            live.url,
            "--participants",
            "2",
            "--concurrency",
            "2",
            "--rounds",
            "1",
            "--seed",
            "5",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert completed.returncode == 0, completed.stderr
    assert "participants completed  2 of 2" in completed.stdout
    acknowledged = int(completed.stdout.split("events acknowledged")[1].split()[0])
    assert acknowledged == count_events(db)
    for kind in ("move", "agent_step", "finish"):
        assert kind in completed.stdout
    bad = subprocess.run(
        [
            sys.executable,
            "-m",
            "server.commands.main",
            "teach",
            "--url",
            live.url,
            "--rounds",
            "3-1",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert bad.returncode == 2 and "--rounds" in bad.stderr
