"""Learner updates on a Dask cluster (``BAM_UPDATE_SCHEDULER``): the server is ready once the
workers are warm, participants teach, a worker killed during an update loses nothing, and the
evaluations equal those of the same participants with local update processes, to the last bit.
"""

from __future__ import annotations

import logging
import os
import random
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pandas as pd
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from analysis.columns import EVALUATION_COLUMNS
from server.app.export.tables import export_tables
from server.app.main import create_app
from server.app.participants import tokens
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import LearnerUpdate, LearningSession
from server.domains import make
from server.domains.base import ACTIONS
from server.teacher import Teacher
from tests.app.updates.test_updates import SLOW_STUDY, demonstrate
from tests.support.databases import migrated_sqlite
from tests.support.server import (
    Participant,
    free_port,
    make_settings,
    study_config,
    teaching_participant,
    wait_for_updates,
    wait_until_ready,
)

distributed = pytest.importorskip("distributed")

# The evaluations' columns that depend on the inputs only (not on when or how fast).
SAME_COLUMNS = [*EVALUATION_COLUMNS, "status", "objective"]


@pytest.fixture(scope="module")
def cluster() -> Iterator[Any]:
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as local_cluster:
        yield local_cluster


def fresh_database(path: Path) -> Database:
    return Database.from_url(migrated_sqlite(path))


def agent_try(participant: Participant, session_id: int, task: int, steps: int) -> None:
    """The agent acts ``steps`` times on ``task`` (each step waits for the session's pending
    update) and the teacher gives its feedback on each."""
    base = participant.session(session_id)
    env = make(participant.get(base)["summary"]["environment"])
    teacher = Teacher(env, seed=task)
    if participant.get(base)["teaching"]["task"] != task:
        participant.act(f"{base}/task", task=task)
    participant.act(f"{base}/reset")
    participant.act(f"{base}/mode", mode="agent")
    for _ in range(steps):
        data = participant.act(f"{base}/agent-step")
        outcome = data["outcome"]
        signal_ = teacher.feedback(task, outcome["state"], ACTIONS.index(outcome["action"]))
        if signal_:
            participant.act(f"{base}/feedback", feedback=signal_)
        if outcome["episode_ended"]:
            return
    participant.act(f"{base}/end-episode")


def teach(client: TestClient, during_updates: Any = None) -> None:
    """Two participants, each: three demonstrations and an agent's try with feedback, in a
    fixed order. ``during_updates()`` is called once, after the first demonstrations."""
    wait_until_ready(client)
    participants = [teaching_participant(client, f"W{k}", f"A{k}") for k in range(2)]
    for task in range(3):
        for participant, session_id in participants:
            demonstrate(participant, session_id, task, seed=task)
        if task == 0 and during_updates is not None:
            during_updates()
    for participant, session_id in participants:
        agent_try(participant, session_id, 0, steps=4)


def evaluations(db: Database) -> pd.DataFrame:
    return export_tables(db)["evaluations"][SAME_COLUMNS]


def learner_states(db: Database) -> list[tuple[int, int, bytes | None, bytes | None]]:
    with db.read() as s:
        return [
            (row.session_id, row.update_index, row.learner_state, row.greedy_policy)
            for row in s.scalars(
                select(LearnerUpdate).order_by(LearnerUpdate.session_id, LearnerUpdate.update_index)
            )
        ]


def executing(dask_worker: Any) -> list[str]:
    """In a worker, through ``Client.run``: the tasks it is running."""
    return [str(task.key) for task in dask_worker.state.executing]


class WorkerKiller(threading.Thread):
    """Kills the process of the first worker seen starting a learner update that fits the
    learner (update 1 or later; they take about two seconds here): its nanny starts another."""

    def __init__(self, client: Any) -> None:
        super().__init__(daemon=True)
        self.client = client
        self.killed: str | None = None
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            pids = self.client.run(os.getpid)
            seen = {key for keys in self.client.run(executing).values() for key in keys}
            deadline = time.monotonic() + 120
            while self.killed is None and time.monotonic() < deadline:
                for address, keys in self.client.run(executing).items():
                    fresh = [key for key in keys if key not in seen]
                    seen.update(keys)
                    if any(int(key.split("-")[3]) >= 1 for key in fresh):
                        os.kill(pids[address], signal.SIGKILL)
                        self.killed = fresh[0]
                        return
                time.sleep(0.01)
        except BaseException as error:
            self.error = error


@pytest.mark.slow
def test_a_cluster_gives_the_local_evaluations_and_survives_a_killed_worker(
    tmp_path: Path, cluster: Any, executor: ProcessPoolExecutor, monkeypatch: pytest.MonkeyPatch
) -> None:
    study = study_config(**SLOW_STUDY)
    outcomes = {}
    for where in ("local", "cluster"):
        # The same participants: the same domains, learner orders and session seeds.
        monkeypatch.setattr(tokens, "SYSTEM_RANDOM", random.Random(22))
        db = fresh_database(tmp_path / f"{where}.db")
        url = db.engine.url.render_as_string(hide_password=False)
        if where == "local":
            app = create_app(make_settings(url), study, db=db, executor=executor)
            with TestClient(app) as client:
                teach(client)
                wait_for_updates(db)
        else:
            settings = make_settings(url, update_scheduler=cluster.scheduler_address)
            with (
                distributed.Client(cluster.scheduler_address) as observer,
                TestClient(create_app(settings, study, db=db)) as client,
            ):
                health = wait_until_ready(client)
                assert health["update_scheduler"] == cluster.scheduler_address
                assert health["update_processes"] == health["update_processes_warm"] == 2
                killer = WorkerKiller(observer)
                teach(client, killer.start)
                killer.join()
                assert killer.error is None and killer.killed is not None, killer.error
                wait_for_updates(db)
        outcomes[where] = (evaluations(db), learner_states(db))
        with db.read() as s:
            rows = s.scalars(select(LearnerUpdate)).all()
            assert rows and all(row.status == "done" for row in rows)
            retried = [(row.attempts, row.error) for row in rows if row.attempts > 1]
        if where == "cluster":  # the killed worker's update ran again elsewhere, and says so
            assert retried == [(2, "the update process died")]
        else:
            assert retried == []
        db.dispose()
    local, on_cluster = outcomes["local"], outcomes["cluster"]
    assert len(local[0]) == 2 * 5  # update 0, three demonstrations, the agent's try
    pd.testing.assert_frame_equal(local[0], on_cluster[0], check_exact=True)
    assert local[1] == on_cluster[1]


@pytest.mark.slow
def test_the_server_waits_for_a_worker_and_its_warm_up(tmp_path: Path) -> None:
    """With a scheduler and no worker, /api/health answers 503; a worker joins, warms up, and
    the server becomes ready and runs the updates."""
    db = fresh_database(tmp_path / "study.db")
    with distributed.LocalCluster(
        n_workers=0, threads_per_worker=1, processes=True, dashboard_address=None
    ) as local_cluster:
        settings = make_settings(
            db.engine.url.render_as_string(hide_password=False),
            update_scheduler=local_cluster.scheduler_address,
        )
        with TestClient(create_app(settings, study_config(), db=db)) as client:
            time.sleep(1.0)
            response = client.get("/api/health")
            assert response.status_code == 503
            assert response.json()["update_processes"] == 0
            local_cluster.scale(1)
            health = wait_until_ready(client, timeout=180)
            assert health["update_processes"] == health["update_processes_warm"] == 1
            # The worker loaded the kernels before the server counted it as ready.
            client_ = distributed.Client(local_cluster.scheduler_address)
            try:
                from server.app.updates.cluster import is_warm

                assert list(client_.run(is_warm).values()) == [True]
            finally:
                client_.close()
            participant, session_id = teaching_participant(client)
            demonstrate(participant, session_id, 0)
            wait_for_updates(db)
    db.dispose()


def test_a_bad_scheduler_address_is_one_line_at_start(tmp_path: Path) -> None:
    """An address that is not one, and one where no scheduler answers: a one-line message and
    exit status, before the server starts."""
    database = f"sqlite:///{tmp_path / 'study.db'}"
    command = [sys.executable, "-m", "server.commands.main", "serve", "--port", str(free_port())]
    environment = {**os.environ, "BAM_DATABASE_URL": database}
    for address, status, message in (
        ("localhost:8786", 2, "--update-scheduler='localhost:8786': must be a Dask scheduler"),
        ("tcp://127.0.0.1:1", 1, "cannot connect to the Dask scheduler at tcp://127.0.0.1:1"),
    ):
        result = subprocess.run(
            [*command, "--update-scheduler", address],
            env=environment,
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert result.returncode == status, result.stderr
        last = result.stderr.strip().splitlines()[-1]
        assert last.startswith("bam-study serve: ") and message in last, result.stderr
        assert "Traceback" not in result.stderr
    result = subprocess.run(
        command,
        env={**environment, "BAM_UPDATE_SCHEDULER": "tcp://nowhere"},
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2
    assert "BAM_UPDATE_SCHEDULER='tcp://nowhere': must be a Dask scheduler" in result.stderr


def test_the_scheduler_setting_accepts_dask_addresses_only() -> None:
    assert Settings(update_scheduler="").update_scheduler == ""
    assert Settings(update_scheduler=" tcp://10.0.0.5:8786 ").update_scheduler == (
        "tcp://10.0.0.5:8786"
    )
    assert Settings(update_scheduler="tls://[::1]:8786").update_scheduler == "tls://[::1]:8786"
    for bad in ("10.0.0.5:8786", "http://host:8786", "tcp://host", "tcp://host:8786/x"):
        with pytest.raises(ValueError, match="must be a Dask scheduler address"):
            Settings(update_scheduler=bad)


def die(payload: dict[str, Any]) -> None:
    """An update that kills the process running it."""
    os._exit(1)


def double(payload: dict[str, Any]) -> int:
    return 2 * int(payload["value"])


@pytest.mark.slow
def test_an_update_that_kills_every_worker_comes_back_as_worker_deaths(cluster: Any) -> None:
    """The scheduler gives up on a task whose workers keep dying (allowed-failures, 3): the
    server hears of every death, to count them as attempts, and stops waiting."""
    import asyncio

    from server.app.updates.cluster import UpdateCluster
    from server.app.updates.pool import WorkerDied

    async def scenario() -> tuple[Any, BaseException | None]:
        updates = UpdateCluster.connect(cluster.scheduler_address)
        try:
            answer = await updates.run(double, {"value": 21}, "learner-update-1-1")
            try:
                await asyncio.wait_for(updates.run(die, {}, "learner-update-1-2"), 300)
            except WorkerDied as error:
                return answer, error
            return answer, None
        finally:
            await asyncio.to_thread(updates.close)

    answer, error = run_apart(scenario())
    assert answer == (42, 0)  # the result, and no worker died running it
    assert isinstance(error, WorkerDied) and error.deaths == 4


def run_apart(coroutine: Any) -> Any:
    """``asyncio.run`` in a thread of its own: after the browser tests, this thread may be
    running Playwright's event loop."""
    import asyncio

    with ThreadPoolExecutor(1) as pool:
        return pool.submit(asyncio.run, coroutine).result()


def die_once(payload: dict[str, Any]) -> str:
    """An update whose first attempt kills the process running it."""
    marker = Path(payload["marker"])
    if not marker.exists():
        marker.touch()
        os._exit(1)
    return "ran again"


class Records(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


@pytest.mark.slow
def test_worker_deaths_are_counted_without_a_log_line_per_update(
    cluster: Any, tmp_path: Path
) -> None:
    """The scheduler (in this process: a LocalCluster's) logs nothing at INFO or above for an
    update, while the server still learns how many workers died running each."""
    import asyncio

    from server.app.updates.cluster import UpdateCluster

    async def scenario() -> list[tuple[Any, int]]:
        updates = UpdateCluster.connect(cluster.scheduler_address)
        try:
            answers = [
                await updates.run(double, {"value": k}, f"learner-update-7-{k}") for k in range(4)
            ]
            marker = str(tmp_path / "died")
            answers.append(await updates.run(die_once, {"marker": marker}, "learner-update-8-1"))
            return answers
        finally:
            await asyncio.to_thread(updates.close)

    # Workers killed by the test before come back first: a death then is not this test's.
    cluster.wait_for_workers(2, timeout=120)
    records = Records()
    logger = logging.getLogger("distributed")
    logger.addHandler(records)
    try:
        with ThreadPoolExecutor(1) as pool:
            answers = pool.submit(asyncio.run, scenario()).result()
    finally:
        logger.removeHandler(records)
    assert answers == [(0, 0), (2, 0), (4, 0), (6, 0), ("ran again", 1)]
    lines = [
        f"{record.name}: {record.getMessage()}"
        for record in records.records
        if record.levelno >= logging.INFO
        and record.name.startswith("distributed.")
        and ("out-of-band" in record.getMessage() or "handler" in record.getMessage())
    ]
    assert lines == []


def dask_command(*arguments: str) -> list[str]:
    return [str(Path(sys.executable).with_name("dask")), *arguments]


# The worker runs functions of this module too (``executing``).
DASK_ENVIRONMENT = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[3])}


class SchedulerAndWorker:
    """A Dask scheduler at ``address`` and one single-threaded worker, in processes of their
    own (killed together, as a lost machine is)."""

    def __init__(self, port: int) -> None:
        self.address = f"tcp://127.0.0.1:{port}"
        self.processes = [
            subprocess.Popen(
                dask_command(
                    "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"
                ),
                start_new_session=True,
                env=DASK_ENVIRONMENT,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
        ]
        with distributed.Client(self.address, timeout=60):  # the scheduler answers
            pass
        self.processes.append(
            subprocess.Popen(
                dask_command(
                    "worker", self.address, "--nthreads", "1", "--nworkers", "1", "--no-dashboard"
                ),
                start_new_session=True,
                env=DASK_ENVIRONMENT,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
        )

    def kill(self) -> None:
        for process in reversed(self.processes):
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGKILL)
            process.wait(timeout=30)


class UpdateWatcher(threading.Thread):
    """Waits until the worker runs a learner update that fits the learner (update 1 or later),
    then calls ``then``."""

    def __init__(self, address: str, then: Any) -> None:
        super().__init__(daemon=True)
        self.address = address
        self.then = then
        self.seen: str | None = None
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            with distributed.Client(self.address, timeout=30) as observer:
                deadline = time.monotonic() + 120
                while self.seen is None and time.monotonic() < deadline:
                    for keys in observer.run(executing).values():
                        fitting = [key for key in keys if int(key.split("-")[3]) >= 1]
                        if fitting:
                            self.seen = fitting[0]
                    time.sleep(0.01)
            if self.seen is not None:
                self.then()
        except BaseException as error:
            self.error = error


@pytest.mark.slow
def test_an_update_lost_with_the_scheduler_runs_on_the_next_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The scheduler and its worker are killed while an update runs, and stay away longer than
    the Dask client waits for them; a new scheduler at the same address and a new worker: the
    update was kept pending and runs there, every update of the participant is done, once
    each, with nothing lost, and the new worker was warmed up."""
    from server.app.updates import runners as updates

    monkeypatch.setattr(updates, "CLUSTER_WATCH_SECONDS", 1.0)
    port = free_port()
    first = SchedulerAndWorker(port)
    second: SchedulerAndWorker | None = None
    db = fresh_database(tmp_path / "study.db")
    settings = make_settings(
        db.engine.url.render_as_string(hide_password=False), update_scheduler=first.address
    )
    try:
        with TestClient(create_app(settings, study_config(**SLOW_STUDY), db=db)) as client:
            wait_until_ready(client, timeout=180)
            watcher = UpdateWatcher(first.address, first.kill)
            watcher.start()
            participant, session_id = teaching_participant(client)
            for task in range(3):
                demonstrate(participant, session_id, task, seed=task)
            watcher.join()
            assert watcher.error is None and watcher.seen is not None, watcher.error
            # Longer than the client's own reconnection attempts (10 s, as the server sets).
            time.sleep(12)
            with db.read() as s:
                assert s.scalar(
                    select(func.count())
                    .select_from(LearnerUpdate)
                    .where(LearnerUpdate.status == "pending")
                )
            second = SchedulerAndWorker(port)
            wait_for_updates(db, timeout=180)
            with db.read() as s:
                rows = s.scalars(select(LearnerUpdate).order_by(LearnerUpdate.update_index))
                done = [(row.update_index, row.status, row.attempts, row.error) for row in rows]
                session = s.get(LearningSession, session_id)
                assert session is not None
                requested, processed = session.updates_requested, session.updates_processed
            assert done == [(index, "done", 1, None) for index in range(4)]
            assert requested == processed == 3
            # The new scheduler was given the warm-up: its worker loaded the kernels.
            deadline = time.monotonic() + 60
            while (health := client.get("/api/health").json())["update_processes_warm"] < 1:
                assert time.monotonic() < deadline, health
                time.sleep(0.2)
            assert health["update_processes"] == health["update_processes_warm"] == 1
    finally:
        first.kill()
        if second is not None:
            second.kill()
        db.dispose()


class StandInClient:
    """In place of a Dask client, for the paths a real one reaches only by timing: its status
    is set by the test, and its tasks never end."""

    def __init__(self, status: str) -> None:
        self.status = status
        self.scheduler = type("Rpc", (), {"address": "tcp://127.0.0.1:1"})()
        self.submitted: list[StandInFuture] = []

    def submit(self, function: Any, payload: Any, key: str) -> StandInFuture:
        future = StandInFuture(key)
        self.submitted.append(future)
        return future

    def nthreads(self) -> dict[str, int]:
        return {}

    def scheduler_info(self, n_workers: int) -> dict[str, str]:
        return {"id": f"scheduler-{id(self)}"}


class StandInFuture:
    """A task that never ends: its callbacks are never called."""

    def __init__(self, key: str) -> None:
        self.key = key
        self.status = "pending"

    def add_done_callback(self, callback: Any) -> None:
        pass


@pytest.mark.parametrize("status", ["connecting", "closing", "closed"])
def test_no_update_goes_to_a_client_that_is_not_connected(status: str) -> None:
    """A client that is reconnecting or closing would take the task and, closing, never settle
    it: the update is refused as unavailable (it stays pending and is tried again)."""
    import asyncio

    from server.app.updates.cluster import UpdateCluster
    from server.app.updates.pool import UpdatesUnavailable

    client = StandInClient(status)
    with pytest.raises(UpdatesUnavailable, match=f"the client is {status}"):
        update = UpdateCluster(client).run(double, {"value": 1}, "learner-update-1-1")  # type: ignore[arg-type]
        run_apart(asyncio.wait_for(update, 5))
    assert client.submitted == []


def test_an_update_left_with_a_closed_client_ends_when_the_server_reconnects(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A task the closed client never settled: the reconnection ends the server's wait for it
    with UpdatesUnavailable, instead of leaving the session's updates waiting for ever."""
    import asyncio

    from server.app.updates import cluster as cluster_module
    from server.app.updates.cluster import UpdateCluster
    from server.app.updates.pool import UpdatesUnavailable

    old, new = StandInClient("running"), StandInClient("running")
    monkeypatch.setattr(cluster_module, "connect", lambda *args, **kwargs: new)
    updates = UpdateCluster(old)  # type: ignore[arg-type]

    async def scenario() -> BaseException | None:
        running = asyncio.ensure_future(updates.run(double, {"value": 1}, "learner-update-1-1"))
        await asyncio.sleep(0.05)
        assert len(old.submitted) == 1 and not running.done()
        old.status = "closed"  # it closed without settling the task
        await asyncio.to_thread(updates.workers)  # as the server asks every few seconds
        try:
            await asyncio.wait_for(running, 5)
        except UpdatesUnavailable as error:
            return error
        return None

    error = run_apart(scenario())
    assert isinstance(error, UpdatesUnavailable), error
    assert "lost with the scheduler (pending)" in str(error)
    assert updates.client is new


@pytest.mark.slow
def test_a_study_s_own_environment_is_learned_on_workers_that_never_saw_its_file(
    cluster: Any,
) -> None:
    """The cluster's workers start without the study file: each update's job carries the
    definition of a study's own environment, so the workers learn and score it as the
    server's own processes do, and time the reference updates on it."""
    import asyncio

    from server import domains
    from server.app.study_file import load_study_config
    from server.app.updates.capacity import UpdateCost, measure_updates, reference_jobs
    from server.app.updates.cluster import UpdateCluster
    from server.app.updates.worker import run_update

    examples = Path(__file__).resolve().parents[3] / "server" / "examples"
    study = load_study_config(examples / "office-study.toml")
    before = set(domains.names())
    study.register_environments()
    try:
        (session,) = reference_jobs([("office-floor", "cloning")], lambda name: {}, rounds=1)
        assert session["environment_spec"] == domains.definition("office-floor")
        job = {
            **{key: session[key] for key in ("environment", "environment_spec", "learner")},
            "settings": {},
            "seed": 0,
            "base_state": None,
            "records": [step for episode in session["episodes"] for step in episode],
            "fit": True,
        }
        here = run_update(job)

        async def scenario() -> tuple[dict[str, Any], UpdateCost]:
            updates = UpdateCluster.connect(cluster.scheduler_address)
            try:
                there, _ = await updates.run(run_update, job, "learner-update-office-1")
                cost, _ = await updates.run(
                    measure_updates, {"jobs": [session]}, "learner-update-office-reference"
                )
                return there, cost
            finally:
                await asyncio.to_thread(updates.close)

        with ThreadPoolExecutor(1) as pool:
            there, cost = pool.submit(asyncio.run, scenario()).result()
    finally:
        for name in set(domains.names()) - before:
            domains.unregister(name)
    assert there["greedy_policy"] == here["greedy_policy"]
    assert there["normalized_return"] == here["normalized_return"]
    assert 0 < cost.mean_seconds <= cost.longest.seconds
    assert (cost.longest.environment, cost.longest.learner) == ("office-floor", "cloning")
