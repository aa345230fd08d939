"""How many participants can teach at once without waiting for their agents.

Each active participant queues a learner update every ``update_interval_seconds`` on average
(an episode end, or a new agent's untrained learner); the update slots (local update processes,
or the Dask cluster's worker threads) each run one update at a time, taking ``update_seconds``
(the measured wall time of one). Updates that someone waits for go first (``updates``), so a
participant waits about one update as long as the slots are busy less than
``TARGET_UTILISATION`` of the time; the capacity is the participant count that keeps them so:

    capacity = TARGET_UTILISATION x slots x update_interval_seconds / update_seconds

Where the slots are processes on the server's own machine, its cores also do the server's own
work for each update (``server_seconds``: the participants' requests and the update's reading
and storing, CPU seconds of the server's process per update), and the capacity is at most

    TARGET_UTILISATION x cores x update_interval_seconds / (update_seconds + server_seconds)

The costs are measured at start on the study's own learners and environments
(``reference_jobs``, ``measure_updates``, in an update process; the server's own work on a
scratch copy of the study, ``server.commands.server_share``), then from the updates the server
runs and its process's CPU time meanwhile, with that of a PostgreSQL server on the same machine
(``server.app.storage.database_cpu``). Where the slots share the server's cores, a live update's
cost is its CPU time, not its wall time: under load its wall time also counts the moments the
server's or the database's work held its core, which ``server_seconds`` counts already (on
PostgreSQL on the same machine at 100 participants an update's wall time was more than twice
its CPU time, and the capacity read 59 with it while 100 participants waited under 1 s).

Several servers of a deployment state a capacity each; the deployment's is summed per machine
(``deployment_participants``): servers on one machine share its cores, so their slots are
summed and the cores bound above is applied once for all of them (three servers with one update
process each on a 2-core machine have the capacity of 2 cores, not of 6), and servers that send
their updates to one Dask cluster share its workers, counted once.

The capacity bounds the queue, not one update's own time: an agent step that follows an update
waits for it however few participants teach. The longest reference update is said beside the
capacity (``LongestUpdate``): where it takes seconds (a slow CPU, a large environment), the
participants of that environment wait that long at any capacity.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

# Busier than this, queues grow faster than the priority of awaited updates can hide.
TARGET_UTILISATION = 0.75
# Rounds of demonstrations (every task once) of the reference sessions: the most the simulated
# participants of benchmarks/server.py teach an agent (2 to 4). An update costs more as the data
# grow (the paper's study on an AMD EPYC: 0.101 s a session's update on average over 2 rounds,
# 0.117 s over 4), and shorter sessions overstated the capacity.
REFERENCE_ROUNDS = 4
LIVE_UPDATES = 200  # the updates the live cost is the mean of
LIVE_MINIMUM = 30  # fewer run since the start: the reference cost still stands


@dataclass(frozen=True)
class LongestUpdate:
    """The longest update of the reference sessions: what an agent step that follows such an
    update waits with no queue at all."""

    seconds: float
    environment: str
    learner: str


@dataclass(frozen=True)
class UpdateCost:
    """What timing reference sessions found: the mean wall time of an update over all of
    them, and the longest update's (wall seconds, its environment and learner)."""

    mean_seconds: float
    longest: LongestUpdate


@dataclass(frozen=True)
class Capacity:
    participants: int  # teaching at once without waiting
    # Wall time of one update (live, where the slots share the server's cores: its CPU time)
    update_seconds: float
    slots: int  # updates run at once
    update_interval_seconds: float  # how often an active participant queues an update
    measured_on: str  # what the update cost was measured on
    longest_update: LongestUpdate | None = None  # of the reference sessions, once timed
    # The server process's CPU seconds per update (live: with a PostgreSQL server's on this
    # machine), where the slots share its cores (None: not counted: the slots are a
    # cluster's, or it could not be timed).
    server_seconds: float | None = None


def participants_at_once(
    update_seconds: float,
    slots: int,
    update_interval_seconds: float,
    server_seconds: float = 0.0,
    cores: int | None = None,
) -> int:
    """The capacity (module docstring); at least 1. ``cores``: the cores the slots share with
    the server's process (None: the slots are elsewhere, a cluster's workers)."""
    if update_seconds <= 0:
        raise ValueError("an update takes some time")
    if server_seconds < 0:
        raise ValueError("the server's work per update is not negative")
    share = TARGET_UTILISATION * max(1, slots) * update_interval_seconds / update_seconds
    if cores is not None:
        shared = update_interval_seconds / (update_seconds + server_seconds)
        share = min(share, TARGET_UTILISATION * max(1, cores) * shared)
    return max(1, math.floor(share))


@dataclass(frozen=True)
class ServerSlots:
    """One server's update slots as its heartbeat states them, for the deployment's capacity."""

    machine: str  # where the slots run (``servers.slots_machine``): the same one shares cores
    slots: int
    cores: int | None  # the cores the slots share with the server there (None: a cluster's)
    update_seconds: float  # an update's cost the server's capacity was stated from
    server_seconds: float | None  # the server's own work per update (None: not counted)


def deployment_participants(
    servers: Iterable[ServerSlots], update_interval_seconds: float
) -> tuple[int, int]:
    """The participants at once and the update slots of a deployment's ``servers``
    (the module docstring): on each machine, its servers' slots summed (a cluster's: its
    workers once) with their costs' mean weighted by slots, its cores counted once; the
    machines' capacities summed."""
    machines: dict[str, list[ServerSlots]] = {}
    for server in servers:
        machines.setdefault(server.machine, []).append(server)
    participants = slots = 0
    for group in machines.values():
        local = [server for server in group if server.cores is not None]
        if local:  # processes on the machine: their slots add up, its cores do not
            cores = max(server.cores or 1 for server in local)
            summed = sum(max(1, server.slots) for server in local)
            participants += participants_at_once(
                _mean(local, lambda server: server.update_seconds),
                summed,
                update_interval_seconds,
                _mean(local, lambda server: server.server_seconds or 0.0),
                cores=cores,
            )
            slots += min(summed, cores)
        cluster = [server for server in group if server.cores is None]
        if cluster:  # the same workers, whichever server sends them updates
            widest = max(max(1, server.slots) for server in cluster)
            participants += participants_at_once(
                _mean(cluster, lambda server: server.update_seconds),
                widest,
                update_interval_seconds,
            )
            slots += widest
    return participants, slots


def _mean(servers: list[ServerSlots], cost: Callable[[ServerSlots], float]) -> float:
    """A cost's mean over ``servers``, weighted by their slots."""
    weights = [max(1, server.slots) for server in servers]
    return sum(w * cost(s) for w, s in zip(weights, servers, strict=True)) / sum(weights)


def reference_jobs(
    pairs: Iterable[tuple[str, str]],
    settings_of: Callable[[str], dict[str, Any]],
    rounds: int = REFERENCE_ROUNDS,
) -> list[dict[str, Any]]:
    """A learning session for each (environment, learner), as ``measure_updates`` replays
    it: the untrained learner, then ``rounds`` rounds of the simulated teacher's
    demonstrations (every task once a round), one episode at a time."""
    from server.domains import definition, make
    from server.domains.base import STAY
    from server.learners.records import DemonstrationStep
    from server.teacher import Teacher

    sessions = []
    for environment, learner in pairs:
        env = make(environment)
        teacher = Teacher(env, seed=0)
        rng = np.random.default_rng(0)
        episodes: list[list[DemonstrationStep]] = []
        for _ in range(rounds):
            for task in range(len(env.tasks)):
                start = int(rng.choice(env.num_states, p=env.tasks[task].start))
                steps = teacher.demonstration(task, start)
                records = [
                    DemonstrationStep(task, state, action, next_state)
                    for state, action, next_state in steps
                ]
                if steps:  # the synthetic STAY that ends a demonstration
                    end = steps[-1][2]
                    records.append(DemonstrationStep(task, end, STAY, env.step(end, STAY, rng)))
                episodes.append(records)
        sessions.append(
            {
                "environment": environment,
                "environment_spec": definition(environment),
                "learner": learner,
                "settings": settings_of(learner),
                "seed": 0,
                "episodes": episodes,
            }
        )
    return sessions


def session_updates(session: dict[str, Any]) -> list[list[Any]]:
    """The records of each update a reference session runs: none for update 0 (the untrained
    learner), then one episode's for each later update."""
    return [[], *session["episodes"]]


def measure_updates(request: dict[str, Any]) -> UpdateCost:
    """In an update process: the wall time of the updates of ``request["jobs"]``
    (``reference_jobs``), each session's run as the server runs them: update 0 (the untrained
    learner), then one update per episode from the learner state the one before saved. The
    first session is run once untimed first, to load whatever the process has not loaded
    (unless ``request["warm"]`` is false: the process has run one already)."""
    from server.app.updates.worker import run_update

    sessions = request["jobs"]
    if not sessions:
        raise ValueError("no reference update to time")

    def replay(session: dict[str, Any]) -> list[float]:
        seconds = []
        state = None
        for index, records in enumerate(session_updates(session)):
            job = {
                **{
                    key: session.get(key)
                    for key in ("environment", "environment_spec", "learner", "settings", "seed")
                },
                "base_state": state,
                "records": records,
                "fit": index > 0,
                "threads": 1,
            }
            started = time.perf_counter()
            state = run_update(job)["learner_state"]
            seconds.append(time.perf_counter() - started)
        return seconds

    if request.get("warm", True):
        replay(sessions[0])
    timed = [(session, replay(session)) for session in sessions]
    session, seconds = max(timed, key=lambda pair: max(pair[1]))
    return UpdateCost(
        mean_seconds=float(np.mean([x for _, times in timed for x in times])),
        longest=LongestUpdate(max(seconds), str(session["environment"]), str(session["learner"])),
    )


def measure_update_cost(request: dict[str, Any]) -> float:
    """``measure_updates``' mean wall time of an update."""
    return measure_updates(request).mean_seconds


def longest_of(costs: Iterable[UpdateCost]) -> LongestUpdate:
    """The longest update of several timings."""
    return max((cost.longest for cost in costs), key=lambda longest: longest.seconds)


def describe(capacity: Capacity) -> str:
    """The line ``serve`` prints."""
    return (
        f"Capacity: {capacity.participants} participants teaching at once without waiting "
        f"for their agents ({capacity.slots} update slot(s), an update takes "
        f"{capacity.update_seconds:.2f} s measured on {capacity.measured_on}"
        + (
            f", the server's own work {capacity.server_seconds:.2f} s of a core per update"
            if capacity.server_seconds is not None
            else ""
        )
        + f", a participant queues one every {capacity.update_interval_seconds:.0f} s, slots "
        f"busy at most {TARGET_UTILISATION:.0%})."
        + (f" {waits(capacity.longest_update)}" if capacity.longest_update is not None else "")
    )


def waits(longest: LongestUpdate) -> str:
    """What the longest reference update means for the participants, in a sentence."""
    return (
        f"The longest update, {longest.learner} in {longest.environment}, takes "
        f"{longest.seconds:.2f} s: an agent that follows one is ready that long after its "
        "episode ends, however few participants teach."
    )
