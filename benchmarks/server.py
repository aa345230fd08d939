"""Study server benchmark: a live server, N simulated participants teaching at once
over HTTP, p50 and p95 latencies of moves, agent steps and waits for learner updates, and events
acknowledged against events stored.

    python benchmarks/server.py                               # 200 participants, 300 s, SQLite
    python benchmarks/server.py --participants 50 --seconds 60 --database-url postgresql+psycopg://...
    python benchmarks/server.py --scheduler local:2             # updates on a local Dask cluster
    python benchmarks/server.py --scheduler tcp://host:8786     # ... or on a running one
    python benchmarks/server.py --servers 3 --database-url postgresql+psycopg://...
                                                   # three servers behind nginx, one database
    python benchmarks/server.py --dashboards 3                  # with three live dashboards open
    python benchmarks/server.py --dashboards 3 --alternate 10   # ... open and closed in turns

The server is ``bam-study serve`` in its own process (a fresh SQLite file in a temporary folder
unless --database-url is given; a PostgreSQL database is migrated first), with the paper's study
and its learners at their reference settings (--fast-learners: far fewer optimisation steps).
Participants arrive spread over --ramp-seconds and act at a person's pace: a pause of about
--think-seconds before each move, --agent-step-seconds before each agent step (the page
animates the agent every half second) and --episode-pause-seconds before each episode. After
--seconds they stop sending; requests in flight are answered, then every acknowledged request
must be stored. An agent step that had to wait for its learner's update counts as an update
wait, not as an agent step (the agent's wait for its update: the figure that updates on a Dask
cluster, --scheduler, are for). Latencies run from a request's first attempt, and the table counts
the requests that needed a retry.

With --servers N (PostgreSQL), N ``serve`` processes share the database behind Debian's nginx
(``server.commands.live.Proxy``, docs/deployment.md's configuration), each with --workers update
processes, and the participants go through the proxy; the capacity is the deployment's (every
server's, once each has timed its own), and the servers' CPU is their sum.

With --dashboards N, N live dashboards follow the funnel, the curves and one participant's
mirror each (from a process of their own, as a researcher's browser is), and the delay from a
participant's event to the mirror that shows it is timed. With --alternate SECONDS they are open
and closed in turns from the end of the arrivals on, and the moves sent in open turns are
compared with those sent in closed ones of the same run (between runs, the moves' p95 varies
more than the rise to be judged).

The server measures its capacity at start (the participants who can teach at once without
waiting, ``server.app.capacity``); the participants arrive once it has, so that the measurement
does not compete with them, and the study lets all of them in at once (max_active_participants).
After they stop, the updates still pending are counted 10 s later, and the time they took to
drain is given.

The participant's target, on a 2-core machine with SQLite at the defaults: 200 participants for
300 s, the agent's wait for its update p95 at most 2 s, a move p95 at most 50 ms, nothing lost,
no update pending 10 s after the participants stop.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import multiprocessing
import os
import secrets
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

# This file is benchmarks/server.py: run as a script, its folder comes first on sys.path and
# would shadow the ``server`` package.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import httpx
import numpy as np
from sqlalchemy import func, select

from server.app.storage.db import Database, upgrade
from server.app.storage.models import Event, LearnerUpdate
from server.app.study_file import DEFAULT_STUDY_CONFIG
from server.commands.live import Proxy, ServerProcess, free_port
from server.commands.simulated import (
    STUDY_PLAN,
    StudyRun,
    latency_row,
    percentile,
    run_participants,
)
from server.learners.settings import OPTIMIZERS

FAST_LEARNERS: dict[str, dict[str, object]] = {
    "bam": {"alternations": 2, "cost_steps": 10, "dynamics_steps": 10},
    "model-based": {"dynamics_steps": 20, "cost_steps": 20},
}
PLANNER_LEARNERS = ("bam", "model-based")  # those of the paper's study
# The participant's target (module docstring).
WAIT_P95_SECONDS = 2.0
MOVE_P95_SECONDS = 0.050
DRAINED_WITHIN_SECONDS = 10.0
MIRROR_P95_SECONDS = 1.0  # a participant's move on the dashboard's mirror (--dashboards)
MOVE_RISE_WITH_DASHBOARDS = 0.10  # the move p95's rise with them open (--alternate)
ALTERNATE_SETTLE_SECONDS = 1.0  # the start of each turn, left out (streams opening or closing)
DRAIN_WATCH_SECONDS = 120.0  # how long the drain of the updates is followed after the stop


def learner_settings_toml(
    fast: bool, optimizer: str | None, warm_alternations: int | None = None
) -> str:
    """The study file's [learner_settings] tables for --fast-learners, --optimizer and
    --warm-alternations."""
    tables: dict[str, dict[str, object]] = {}
    if fast:
        for name, settings in FAST_LEARNERS.items():
            tables.setdefault(name, {}).update(settings)
    if optimizer is not None:
        for name in PLANNER_LEARNERS:
            tables.setdefault(name, {})["optimizer"] = optimizer
    if warm_alternations is not None:
        tables.setdefault("bam", {})["warm_alternations"] = warm_alternations
    lines = []
    for name, settings in tables.items():
        lines.append(f'\n[learner_settings."{name}"]')
        lines += [f"{key} = {json.dumps(value)}" for key, value in settings.items()]
    return "\n".join(lines) + "\n"


CLOCK_TICKS = os.sysconf("SC_CLK_TCK")


def _proc_stat(pid: int) -> tuple[int, float] | None:
    """A process's parent and CPU seconds so far (user + system), from /proc; None once gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text[text.rindex(")") + 2 :].split()  # after the command name, which may hold spaces
    return int(fields[1]), (int(fields[11]) + int(fields[12])) / CLOCK_TICKS


def cpu_by_group(server_pid: int, cluster_pids: list[int]) -> dict[str, float]:
    """CPU seconds so far of the server's own process, of its descendants (the update
    processes), of a local Dask cluster's processes and their descendants, of this benchmark (the
    simulated participants), and of the whole machine (busy, from /proc/stat)."""
    stats = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and (stat := _proc_stat(int(entry.name))) is not None:
            stats[int(entry.name)] = stat

    def tree(root: int) -> set[int]:
        found, frontier = {root}, [root]
        while frontier:
            parent = frontier.pop()
            children = [pid for pid, (ppid, _) in stats.items() if ppid == parent]
            found.update(children)
            frontier += children
        return found

    def seconds(pids: set[int]) -> float:
        return sum(stats[pid][1] for pid in pids if pid in stats)

    updates = tree(server_pid) - {server_pid}
    cluster = set().union(*(tree(pid) for pid in cluster_pids)) if cluster_pids else set()
    own = os.times()
    line = Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]
    ticks = [int(x) for x in line]
    idle = ticks[3] + ticks[4]  # idle and iowait
    return {
        "server": seconds({server_pid}),
        "update processes": seconds(updates),
        "Dask cluster": seconds(cluster),
        "simulated participants": own.user + own.system,
        "machine": (sum(ticks[:8]) - idle) / CLOCK_TICKS,
    }


def core_use_line(before: dict[str, float], after: dict[str, float], seconds: float) -> str:
    """The cores each group used on average between two ``cpu_by_group`` readings; "other" is
    the rest of the machine's busy time (a PostgreSQL server on it, say)."""
    used = {name: (after[name] - before[name]) / seconds for name in before}
    groups = [name for name in used if name != "machine" and (used[name] > 0.005)]
    other = used["machine"] - sum(used[name] for name in groups)
    parts = [f"{name} {used[name]:.2f}" for name in groups] + [f"other {max(0.0, other):.2f}"]
    return f"cores used (of {os.cpu_count()})      " + ", ".join(parts)


@contextlib.contextmanager
def local_cluster(workers: int, folder: Path) -> Iterator[tuple[str, list[int]]]:
    """A Dask scheduler and ``workers`` single-threaded worker processes beside the server,
    started as on other machines (``dask scheduler``, ``dask worker``), at the niceness of
    local update processes; yields the scheduler's address and the two processes' ids."""
    address = f"tcp://127.0.0.1:{free_port()}"
    port = address.rsplit(":", 1)[1]
    cli = [sys.executable, "-m"]
    commands = [
        [*cli, "distributed.cli.dask_scheduler", "--port", port, "--no-dashboard"],
        [
            "nice",
            "-n",
            "10",
            *cli,
            "distributed.cli.dask_worker",
            address,
            "--nworkers",
            str(workers),
            "--nthreads",
            "1",
            "--no-dashboard",
        ],
    ]
    processes = []
    try:
        for name, command in zip(("scheduler", "workers"), commands, strict=True):
            with open(folder / f"dask-{name}.log", "wb") as log:
                processes.append(
                    subprocess.Popen(
                        command, stdout=log, stderr=subprocess.STDOUT, start_new_session=True
                    )
                )
        yield address, [process.pid for process in processes]
    finally:
        for process in reversed(processes):
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGTERM)
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()


def pending_updates(db: Database) -> int:
    with db.read() as s:
        return int(
            s.scalar(
                select(func.count())
                .select_from(LearnerUpdate)
                .where(LearnerUpdate.status == "pending")
            )
            or 0
        )


def queue_view(url: str, token: str) -> dict[str, object]:
    """The server's queue view (``/api/admin/queue``)."""
    answer = httpx.get(
        f"{url}/api/admin/queue", headers={"Authorization": f"Bearer {token}"}, timeout=10
    )
    answer.raise_for_status()
    queue: dict[str, object] = answer.json()
    return queue


def wait_for_capacity(url: str, token: str, timeout: float) -> dict[str, object]:
    """The server's queue view once it has measured its capacity."""
    deadline = time.monotonic() + timeout
    while True:
        queue = queue_view(url, token)
        if queue["capacity"] is not None:
            return queue
        if time.monotonic() > deadline:
            raise RuntimeError(f"the server did not measure its capacity within {timeout:.0f} s")
        time.sleep(1.0)


def capacity_line(queue: dict[str, object], when: str = "") -> str:
    """The capacity the server states (``when``: at start unless said), as its queue view
    gives it; the server's own work per update is timed only where the updates share its cores
    (not on a Dask cluster)."""
    server = queue["server_seconds_per_update"]
    own = (
        "its own work per update not counted (the updates run on the cluster's cores)"
        if server is None
        else f"the server's own work {server} s a core per update"
    )
    return (
        f"the server's capacity{when}: {queue['capacity']} participants at once (an update "
        f"{queue['update_seconds']} s on {queue['measured_on']}, {own}, {queue['slots']} slot(s))"
    )


def follow_drain(db: Database, stopped: float) -> tuple[int, int, float | None]:
    """Pending updates at the stop (``stopped``, a perf_counter time) and 10 s after it, and
    how long after it none was left (None: not within ``DRAIN_WATCH_SECONDS``)."""
    at_stop = pending_updates(db)
    at_mark: int | None = None
    while True:
        now = time.perf_counter() - stopped
        pending = pending_updates(db)
        if at_mark is None and now >= DRAINED_WITHIN_SECONDS:
            at_mark = pending
        if pending == 0:
            return at_stop, at_mark if at_mark is not None else 0, now
        if now > DRAIN_WATCH_SECONDS:
            return at_stop, at_mark if at_mark is not None else pending, None
        time.sleep(0.5)


def busy_share(
    updates: list[tuple[datetime | None, float | None, float | None]],
    slots: object,
    since: datetime,
    until: datetime,
) -> float:
    """The share of the slots' time from ``since`` to ``until`` that the updates finished
    then took (their fit and evaluation, ``updates``: finished at, seconds, evaluation
    seconds; an update running across ``since`` counts whole)."""
    assert isinstance(slots, int)
    busy = sum(
        (fit or 0.0) + (evaluation or 0.0)
        for finished, fit, evaluation in updates
        if finished is not None and since <= finished <= until
    )
    return busy / (max(1, slots) * max(1e-9, (until - since).total_seconds()))


def drain_watch(db: Database, stopped: float) -> Callable[[], tuple[int, int, float | None]]:
    """``follow_drain`` in a thread of its own from the stop on, while the participants' own
    threads end (those waiting for an agent's update end only when they get it, which took
    longer than 10 s at 200 participants: read after them, the readings at the stop and 10 s
    after it were one); the function returned waits for its answer."""
    answer: list[tuple[int, int, float | None]] = []
    watcher = threading.Thread(target=lambda: answer.append(follow_drain(db, stopped)))
    watcher.start()

    def result() -> tuple[int, int, float | None]:
        watcher.join()
        return answer[0]

    return result


def sse_events(response: httpx.Response) -> Iterator[dict[str, object]]:
    """The data of each server-sent event of a stream."""
    data = None
    for line in response.iter_lines():
        if line.startswith("data:"):
            data = line.removeprefix("data:").strip()
        elif line == "" and data is not None:
            yield json.loads(data)
            data = None


class Dashboards:
    """``count`` dashboards open on the live views while the participants teach, as the live
    page opens them: each follows the funnel, the curves and one participant's mirror (a participant who is
    teaching, another once that one has finished). The mirror's delay: from a participant's
    event committed (its time in the view) to the view that shows it received here.

    Open for the whole run, or (``alternate``) open and closed in turns of that many seconds
    from the end of the arrivals on, each turn's times kept in ``phases``."""

    def __init__(self, url: str, token: str, count: int, stop: Any = None) -> None:
        self.url, self.token, self.count = url, token, count
        self.run_stop = stop if stop is not None else threading.Event()  # the run's stop
        self.stop = threading.Event()  # this opening's: set at the run's stop or a turn's end
        self.delays: list[float] = []
        self.snapshots: dict[str, int] = {}  # received, by view
        self.errors: list[str] = []
        self.threads: list[threading.Thread] = []
        self.lock = threading.Lock()
        self.watched: set[int] = set()
        self.clients: list[httpx.Client] = []
        self.phases: list[Phase] = []
        self.watched_count = 0  # over every opening

    def client(self) -> httpx.Client:
        client = httpx.Client(
            base_url=self.url,
            headers={"Authorization": f"Bearer {self.token}"},
            timeout=httpx.Timeout(30.0, read=60.0),
        )
        with self.lock:
            self.clients.append(client)
        return client

    def seen(self) -> dict[str, Any]:
        """What they saw, in plain values (sent from their process to the benchmark's)."""
        return {
            "delays": self.delays,
            "snapshots": self.snapshots,
            "watched_count": self.watched_count,
            "errors": self.errors,
            "phases": [dataclasses.astuple(phase) for phase in self.phases],
        }

    def take(self, seen: dict[str, Any]) -> None:
        """``seen()`` of the dashboards' process, here."""
        self.delays, self.snapshots, self.errors = seen["delays"], seen["snapshots"], seen["errors"]
        self.watched_count = seen["watched_count"]
        self.phases = [Phase(*phase) for phase in seen["phases"]]

    def open(self) -> None:
        """Open every dashboard: its funnel stream and its mirror."""
        self.stop = threading.Event()
        self.watched = set()  # a new opening watches whoever is teaching now
        self.threads = [
            threading.Thread(target=target, args=(self.stop,), daemon=True)
            for _ in range(self.count)
            for target in (self.follow_funnel, self.follow_curves, self.follow_mirror)
        ]
        for thread in self.threads:
            thread.start()

    def close(self) -> None:
        """Close every stream, so that the server stops (or goes on) with none open."""
        self.stop.set()
        with self.lock:
            clients, self.clients = self.clients, []
        for client in clients:
            client.close()
        for thread in self.threads:
            thread.join(timeout=10.0)

    def alternate(self, seconds: float, after: float) -> None:
        """Closed and open in turns of ``seconds`` (closed first), from ``after`` seconds on,
        until the run stops; the last turn, cut short by the stop, is not kept."""
        if self.run_stop.wait(after):
            return
        is_open = False
        while True:
            began = time.perf_counter()
            if is_open:
                self.open()
            if self.run_stop.wait(seconds):
                if is_open:
                    self.close()
                return
            if is_open:
                self.close()
            self.phases.append(Phase(began, time.perf_counter(), is_open))
            is_open = not is_open

    def follow_funnel(self, stop: threading.Event) -> None:
        self.follow(stop, "funnel")

    def follow_curves(self, stop: threading.Event) -> None:
        self.follow(stop, "curves")

    def follow(self, stop: threading.Event, view: str) -> None:
        """The live page's stream of ``view`` (the funnel or the curves), until the stop."""
        try:
            with (
                self.client() as client,
                client.stream("GET", f"/api/admin/live/{view}/stream") as r,
            ):
                for _snapshot in sse_events(r):
                    self.snapshots[view] = self.snapshots.get(view, 0) + 1
                    if stop.is_set():
                        return
        except Exception as error:
            if not stop.is_set():
                self.errors.append(f"{view}: {error!r}")

    def someone_teaching(self, client: httpx.Client) -> int | None:
        rows = client.get("/api/admin/live/funnel").json()["participants"]
        with self.lock:
            for row in rows:
                if row["session_id"] is not None and row["participant_id"] not in self.watched:
                    self.watched.add(row["participant_id"])
                    self.watched_count += 1
                    return int(row["participant_id"])
        return None

    def follow_mirror(self, stop: threading.Event) -> None:
        try:
            with self.client() as client:
                while not stop.is_set():
                    participant = self.someone_teaching(client)
                    if participant is None:
                        time.sleep(0.5)
                        continue
                    self.watch(client, participant, stop)
        except Exception as error:
            if not stop.is_set():
                self.errors.append(f"mirror: {error!r}")

    def watch(self, client: httpx.Client, participant: int, stop: threading.Event) -> None:
        newest = None
        path = f"/api/admin/live/participants/{participant}/mirror/stream"
        with client.stream("GET", path) as response:
            for view in sse_events(response):
                received = datetime.now(UTC)
                session = view.get("session")
                if stop.is_set() or not isinstance(session, dict):
                    return  # the turn is over, or the participant is no longer teaching
                recent = session["recent"]
                if not recent:
                    continue
                at = datetime.fromisoformat(recent[0]["at"])
                if newest is not None and at > newest:
                    self.delays.append((received - at).total_seconds())
                newest = at if newest is None else max(newest, at)


def watch_dashboards(
    url: str,
    token: str,
    count: int,
    alternate: float | None,
    after: float,
    stop: Any,
    results: Any,
) -> None:
    """The dashboards' process: open (or open and closed in turns) until ``stop`` (a
    multiprocessing event), then what they saw put on ``results``. A researcher's browser is
    on another machine; here it shares the server's cores, so it runs at the lowest priority
    and takes from the server only the cores it leaves idle."""
    if hasattr(os, "nice"):
        os.nice(19)
    dashboards = Dashboards(url, token, count, stop)
    if alternate is not None:
        dashboards.alternate(alternate, after)
    else:
        dashboards.open()
        stop.wait()
        dashboards.close()
    results.put(dashboards.seen())


@dataclasses.dataclass(frozen=True)
class Phase:
    """One turn of --alternate: from ``began`` to ``ended`` (time.perf_counter), the
    dashboards open or closed."""

    began: float
    ended: float
    open: bool


def p95_rise(
    phases: list[Phase], moves: list[tuple[float, float]], settle: float, seed: int
) -> tuple[list[float], list[float], float, tuple[float, float]]:
    """The moves sent in closed and in open turns (the first ``settle`` seconds of each turn
    left out: streams opening or closing), the open turns' move p95 over the closed turns' less
    one, and its 95% interval from resampling the turns of each kind (the moves of a turn stay
    together: a turn's moves share its load)."""
    by_phase: list[list[float]] = [[] for _ in phases]
    for sent, latency in moves:
        for i, phase in enumerate(phases):
            if phase.began + settle <= sent < phase.ended:
                by_phase[i].append(latency)
                break
    closed = [by_phase[i] for i, phase in enumerate(phases) if not phase.open]
    opened = [by_phase[i] for i, phase in enumerate(phases) if phase.open]

    def rise(a: list[list[float]], b: list[list[float]]) -> float:
        return float(np.percentile(np.concatenate(b), 95) / np.percentile(np.concatenate(a), 95))

    rng = np.random.default_rng(seed)
    draws = [
        rise(
            [closed[i] for i in rng.integers(len(closed), size=len(closed))],
            [opened[i] for i in rng.integers(len(opened), size=len(opened))],
        )
        for _ in range(2000)
    ]
    low, high = np.percentile(draws, [2.5, 97.5])
    flat = [x for turn in closed for x in turn], [x for turn in opened for x in turn]
    return flat[0], flat[1], rise(closed, opened) - 1, (float(low) - 1, float(high) - 1)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--participants", type=int, default=200)
    parser.add_argument("--seconds", type=float, default=300.0, help="how long they teach")
    parser.add_argument("--ramp-seconds", type=float, default=20.0, help="arrivals spread over")
    parser.add_argument("--think-seconds", type=float, default=0.5, help="mean pause per move")
    parser.add_argument("--agent-step-seconds", type=float, default=0.5)
    parser.add_argument("--episode-pause-seconds", type=float, default=2.0)
    parser.add_argument(
        "--database-url",
        help="default: a new SQLite file in a temporary folder; a PostgreSQL URL "
        "(postgresql+psycopg://...) is migrated first",
    )
    parser.add_argument("--workers", type=int, default=2, help="learner-update processes")
    parser.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="run the learner updates on a Dask cluster: a scheduler's address "
        "(tcp://host:8786), or local:N for a scheduler and N worker processes started here",
    )
    parser.add_argument("--fast-learners", action="store_true", help="few optimisation steps")
    parser.add_argument(
        "--optimizer",
        choices=OPTIMIZERS,
        help="the planner learners' optimiser (default: the study file's, the reference)",
    )
    parser.add_argument(
        "--warm-alternations",
        type=int,
        metavar="N",
        help="BAM's momentum alternations before L-BFGS-B (with --optimizer warm-lbfgs)",
    )
    parser.add_argument(
        "--sqlite-synchronous",
        choices=("full", "normal"),
        default="full",
        help="SQLite's synchronous mode (BAM_SQLITE_SYNCHRONOUS; default full)",
    )
    parser.add_argument(
        "--capacity-timeout",
        type=float,
        default=900.0,
        help="how long to wait for the server to measure its capacity at start",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--servers",
        type=int,
        default=1,
        help="serve processes on the one database, behind nginx (PostgreSQL only; 1)",
    )
    parser.add_argument(
        "--dashboards",
        type=int,
        default=0,
        help="live dashboards open meanwhile: each follows the funnel, the curves and one "
        "participant's mirror (the mirror's delay is measured)",
    )
    parser.add_argument(
        "--live-reader",
        choices=("process", "server"),
        default="process",
        help="where the live views read the database (BAM_LIVE_READER; default process)",
    )
    parser.add_argument(
        "--alternate",
        type=float,
        metavar="SECONDS",
        help="with --dashboards: open and close them in turns of SECONDS, from the end of the "
        "arrivals on, and compare the moves' p95 in open turns with closed ones",
    )
    args = parser.parse_args(argv)
    cluster_workers = None
    if args.scheduler and args.scheduler.startswith("local:"):
        count = args.scheduler.removeprefix("local:")
        if not count.isdigit() or int(count) < 1:
            parser.error("--scheduler local:N needs a number of workers N >= 1")
        cluster_workers = int(count)
    if args.warm_alternations is not None:
        if args.warm_alternations < 0:
            parser.error("--warm-alternations must be at least 0")
        if args.optimizer != "warm-lbfgs":
            parser.error("--warm-alternations needs --optimizer warm-lbfgs")

    if args.alternate is not None and (
        args.alternate < 2 * ALTERNATE_SETTLE_SECONDS or not args.dashboards
    ):
        parser.error(
            f"--alternate needs --dashboards and a turn of at least "
            f"{2 * ALTERNATE_SETTLE_SECONDS:.0f} s"
        )
    if args.servers < 1:
        parser.error("--servers must be at least 1")
    if args.servers > 1 and not (args.database_url or "").startswith("postgresql"):
        parser.error(
            "--servers N > 1 needs --database-url postgresql+psycopg://... (a SQLite "
            "study has one server)"
        )
    folder = Path(tempfile.mkdtemp(prefix="bam-bench-"))
    url = args.database_url or f"sqlite:///{folder / 'study.db'}"
    db = Database.from_url(url)
    upgrade(db.engine)
    with db.read() as s:
        events_before = int(s.scalar(select(func.count()).select_from(Event)) or 0)
        updates_before = int(s.scalar(select(func.count()).select_from(LearnerUpdate)) or 0)
    study = folder / "study.toml"
    study.write_text(
        f"max_active_participants = {args.participants}\n"
        + DEFAULT_STUDY_CONFIG.read_text()
        + learner_settings_toml(args.fast_learners, args.optimizer, args.warm_alternations)
    )
    admin_token = secrets.token_urlsafe(16)
    environment = {
        "BAM_ADMIN_TOKEN": admin_token,
        "BAM_DATABASE_URL": url,
        "BAM_STUDY_CONFIG": str(study),
        "BAM_UPDATE_WORKERS": str(args.workers),
        "BAM_SQLITE_SYNCHRONOUS": args.sqlite_synchronous,
        "BAM_LIVE_READER": args.live_reader,
    }
    plan = dataclasses.replace(
        STUDY_PLAN,
        think_seconds=args.think_seconds,
        agent_step_seconds=args.agent_step_seconds,
        episode_pause_seconds=args.episode_pause_seconds,
        retry_seconds=24 * 3600.0,  # a participant waits for the agent until the run stops
    )
    stop = threading.Event()
    result: dict[str, StudyRun] = {}
    if cluster_workers is not None:
        where = f"updates on a local Dask cluster of {cluster_workers} worker processes"
    elif args.scheduler:
        where = f"updates on the Dask cluster at {args.scheduler}"
    else:
        where = f"{args.workers} update processes"
    if args.servers > 1:
        where = f"{args.servers} servers behind nginx, {where} each"
    print(
        f"{args.participants} participants for {args.seconds:.0f} s on "
        f"{'SQLite' if url.startswith('sqlite') else 'PostgreSQL'}, {where}, "
        f"{os.cpu_count()} cores; server log in {folder}",
        flush=True,
    )
    cluster_pids: list[int] = []
    with contextlib.ExitStack() as stack:
        if cluster_workers is not None:
            environment["BAM_UPDATE_SCHEDULER"], cluster_pids = stack.enter_context(
                local_cluster(cluster_workers, folder)
            )
        elif args.scheduler:
            environment["BAM_UPDATE_SCHEDULER"] = args.scheduler
        servers = []
        for number in range(args.servers):
            place = folder if args.servers == 1 else folder / f"server-{number}"
            place.mkdir(exist_ok=True)
            servers.append(stack.enter_context(ServerProcess(place, environment)))
        server = servers[0]
        for each in servers:  # each times its own capacity, one after another
            measured = wait_for_capacity(each.url, admin_token, args.capacity_timeout)
        if args.servers > 1:
            # The deployment's: once every server's heartbeat (every 10 s) has stated its own
            # and the first server has read theirs at its own.
            time.sleep(22.0)
            measured = queue_view(server.url, admin_token)
        print(capacity_line(measured), flush=True)
        entry = server.url
        if args.servers > 1:
            upstreams = [f"127.0.0.1:{each.port}" for each in servers]
            entry = stack.enter_context(Proxy(folder / "nginx", upstreams)).url

        def teach() -> None:
            result["run"] = run_participants(
                entry,
                args.participants,
                args.participants,
                args.seed,
                plan,
                stop=stop,
                ramp_seconds=args.ramp_seconds,
            )

        thread = threading.Thread(target=teach)
        pids = [each.process.pid for each in servers if each.process is not None]

        def cpu() -> dict[str, float]:
            """The servers' CPU (with their update processes), summed."""
            groups = [cpu_by_group(pid, cluster_pids) for pid in pids]
            total = dict(groups[0])  # the machine's, the participants' and a cluster's once
            for group in ("server", "update processes"):
                total[group] = sum(each[group] for each in groups)
            return total

        # The dashboards in a process of their own, as a researcher's browser is: in the
        # participants' process, their threads took the participants' interpreter lock, and
        # the participants' latencies rose by the client's work, not the server's.
        spawn = multiprocessing.get_context("spawn")
        stop_dashboards, watched = spawn.Event(), spawn.Queue()
        watching = spawn.Process(
            target=watch_dashboards,
            args=(
                server.url,
                admin_token,
                args.dashboards,
                args.alternate,
                args.ramp_seconds,
                stop_dashboards,
                watched,
            ),
            daemon=True,
        )
        if args.dashboards:
            watching.start()
        cpu_before = cpu()
        started, started_at = time.perf_counter(), datetime.now(UTC)
        thread.start()
        thread.join(timeout=args.seconds)
        stop.set()
        stop_dashboards.set()
        dashboards = Dashboards(server.url, admin_token, args.dashboards)
        if args.dashboards:
            dashboards_cpu = (_proc_stat(watching.pid or 0) or (0, 0.0))[1]
            dashboards.take(watched.get(timeout=120))
            watching.join(timeout=30)
        stopped, stopped_at = time.perf_counter(), datetime.now(UTC)
        cpu_after = cpu()
        # From the latest updates and, where they share its cores, the server's CPU time (with
        # a PostgreSQL server's on this machine) over them.
        live = queue_view(server.url, admin_token)
        drained = drain_watch(db, stopped)
        thread.join()
        elapsed = time.perf_counter() - started
        at_stop, after_mark, drained_after = drained()
    run = result["run"]
    with db.read() as s:
        stored = int(s.scalar(select(func.count()).select_from(Event)) or 0) - events_before
        updates = dict(
            s.execute(
                select(LearnerUpdate.status, func.count()).group_by(LearnerUpdate.status)
            ).all()
        )
        done = [
            (finished, fit, evaluation)
            for finished, fit, evaluation in s.execute(
                select(
                    LearnerUpdate.finished_at,
                    LearnerUpdate.seconds,
                    LearnerUpdate.evaluation_seconds,
                ).where(LearnerUpdate.status == "done")
            )
        ]
        update_seconds = [fit for _, fit, _ in done]
    db.dispose()

    errors = [p for p in run.participants if p.error]
    requests = sum(len(v) for p in run.participants for v in p.latencies.values())
    print()
    print(f"{'':<26}{'count':>8}{'p50 ms':>10}{'p95 ms':>10}{'max ms':>10}")
    for label, values in (
        ("move", run.latencies("move")),
        ("agent step", run.latencies("agent_step")),
        ("feedback", run.latencies("feedback")),
        (
            "episode end, mode, task, reset",
            [x for kind in ("end_episode", "mode", "task", "reset") for x in run.latencies(kind)],
        ),
        ("wait for an update", run.update_waits),
        ("learner update (server)", [x for x in update_seconds if x is not None]),
        # Requests sent more than once (any kind; a wait for an update is one): their latency
        # above, as here, runs from the first attempt.
        ("retried requests", run.retried_latencies),
    ):
        if values or label == "retried requests":  # none retried is worth saying
            print(latency_row(label, values, 26))
    print()
    print(
        f"requests answered          {requests} ({requests / elapsed:.0f}/s over {elapsed:.0f} s)"
    )
    print(f"events acknowledged        {run.acknowledged}")
    print(f"events stored              {stored}")
    print(f"lost                       {run.acknowledged - stored}")
    print(f"agents finished            {sum(p.sessions for p in run.participants)}")
    print(
        f"learner updates            {updates.get('done', 0)} done, {updates.get('failed', 0)} "
        f"failed; pending: {at_stop} at the stop, {after_mark} "
        f"{DRAINED_WITHIN_SECONDS:.0f} s after it, "
        + (
            f"none after {drained_after:.1f} s"
            if drained_after is not None
            else f"{updates.get('pending', 0)} after {DRAIN_WATCH_SECONDS:.0f} s"
        )
    )
    tries = sum(len(p.latencies.get("agent_step", [])) for p in run.participants)
    print(f"agent steps that waited    {len(run.update_waits)} of {tries + len(run.update_waits)}")
    print(f"capacity stated at start   {measured['capacity']} participants")
    print(capacity_line(live, " at the stop"))
    queued = sum(updates.values()) - updates_before
    # Each participant teaches from its arrival (spread over the ramp) until the stop.
    teaching = args.participants * max(1.0, stopped - started - args.ramp_seconds / 2)
    print(
        f"updates queued             {queued}, one every {teaching / max(1, queued):.1f} s a "
        f"participant (the capacity assumes {measured['update_interval_seconds']:.0f} s)"
    )
    # Updates cost more as an agent's data grow: the run's last minute shows the steady state
    # that its start (fresh agents, cheap updates) hides.
    minute = timedelta(seconds=min(60.0, stopped - started))
    print(
        f"update slots busy          "
        f"{busy_share(done, measured['slots'], started_at, stopped_at):.0%} over the run, "
        f"{busy_share(done, measured['slots'], stopped_at - minute, stopped_at):.0%} over "
        f"its last {minute.total_seconds():.0f} s (the updates' fit and evaluation)"
    )
    print(core_use_line(cpu_before, cpu_after, stopped - started))
    server_cpu = cpu_after["server"] - cpu_before["server"]
    print(f"server CPU per request     {1000 * server_cpu / max(1, requests):.2f} ms")
    if args.dashboards:
        print(
            f"dashboards open            {args.dashboards}: "
            f"{dashboards.snapshots.get('funnel', 0)} funnel and "
            f"{dashboards.snapshots.get('curves', 0)} curves snapshots received, "
            f"{dashboards.watched_count} participants watched; their process used "
            f"{dashboards_cpu / (stopped - started):.2f} cores"
        )
        if dashboards.delays:
            print(latency_row("a move to the mirror", dashboards.delays, 26))
    rise = None
    if args.alternate is not None:
        kept = dashboards.phases
        closed_turns = sum(1 for phase in kept if not phase.open)
        if closed_turns and len(kept) > closed_turns:
            closed, opened, rise, (low, high) = p95_rise(
                kept, run.timed("move"), ALTERNATE_SETTLE_SECONDS, args.seed
            )
            print(
                f"{f'turns of {args.alternate:.0f} s':<27}{closed_turns} closed, "
                f"{len(kept) - closed_turns} open (each turn's first "
                f"{ALTERNATE_SETTLE_SECONDS:.0f} s left out)"
            )
            print(latency_row("move, dashboards closed", closed, 26))
            print(latency_row("move, dashboards open", opened, 26))
            print(
                f"move p95 with them open    {rise:+.1%} (95% interval {low:+.1%} to "
                f"{high:+.1%}, the turns resampled)"
            )
        for problem in dashboards.errors[:5]:
            print(f"  dashboard: {problem}", file=sys.stderr)
    print(f"participants with errors   {len(errors)}")
    for participant in errors[:5]:
        print(f"  participant {participant.index}: {participant.error}", file=sys.stderr)
    moves = run.latencies("move")
    checks = [
        (
            f"agent's wait p95 <= {WAIT_P95_SECONDS:.0f} s",
            percentile(run.update_waits, 95) <= WAIT_P95_SECONDS if run.update_waits else True,
        ),
        (
            f"move p95 <= {MOVE_P95_SECONDS * 1000:.0f} ms",
            percentile(moves, 95) <= MOVE_P95_SECONDS,
        ),
        ("nothing lost", run.acknowledged == stored and not errors),
        *(
            [
                (
                    f"a move reaches the mirror: p95 <= {MIRROR_P95_SECONDS:.0f} s",
                    bool(dashboards.delays)
                    and percentile(dashboards.delays, 95) <= MIRROR_P95_SECONDS,
                )
            ]
            if args.dashboards
            else []
        ),
        *(
            [
                (
                    f"move p95 rises <= {MOVE_RISE_WITH_DASHBOARDS:.0%} with them open",
                    rise is not None and rise <= MOVE_RISE_WITH_DASHBOARDS,
                )
            ]
            if args.alternate is not None
            else []
        ),
        (
            f"no update pending {DRAINED_WITHIN_SECONDS:.0f} s after the stop",
            after_mark == 0,
        ),
    ]
    print()
    for label, met in checks:
        print(f"target: {label:<40} {'met' if met else 'NOT met'}")
    ok = all(met for _, met in checks)
    print(f"the participant's target: {'met' if ok else 'NOT met'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
