"""What runs inside an update process (a local one or a Dask worker): the process's set-up,
and ``run_update``, which restores a learner, replays the events since its last saved state,
updates it and scores its greedy policies."""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
import traceback
from typing import TYPE_CHECKING, Any

import numpy as np

from server.app.storage.vocabulary import Observed
from server.app.updates.policies import encode
from server.domains import register_all
from server.domains.base import STAY
from server.domains.spec import EnvironmentSpec
from server.learners.records import (
    AgentStep,
    DemonstrationStep,
    Feedback,
    IdleMove,
    Observation,
)

if TYPE_CHECKING:
    pass


# -- in the worker process ------------------------------------------------------------------
PARENT_CHECK_SECONDS = 1.0


def serve_the_server(niceness: int, server_pid: int) -> None:
    """A helper process of the server's (an update worker, the live views' reader): Ctrl-C
    ignored, its priority lowered, and gone with the server."""
    # Ctrl-C reaches the whole process group: the server stops its helpers itself (``stop``),
    # and a worker interrupted in its warm-up printed a traceback and broke the pool.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # A server that dies without shutting its pool down (killed, or stopped while it was
    # replacing workers that a SIGTERM to its process group had killed) leaves its workers
    # waiting on a queue no one writes to: they must notice and go. A worker whose server died
    # before it started (its parent is already init) goes at once: comparing with its parent
    # at start would have kept it forever (seen after every benchmarks/server.py run).
    if os.getppid() != server_pid:
        os._exit(0)
    if niceness and hasattr(os, "nice"):
        os.nice(niceness)

    def leave_with_parent() -> None:
        while os.getppid() == server_pid:
            time.sleep(PARENT_CHECK_SECONDS)
        os._exit(0)

    threading.Thread(target=leave_with_parent, name="leave-with-server", daemon=True).start()


def worker_init(
    niceness: int, server_pid: int, environments: tuple[EnvironmentSpec, ...] = ()
) -> None:
    """Lower the worker's priority, leave with the server, import the learners once, know
    the study's own environments."""
    serve_the_server(niceness, server_pid)
    register_all(environments)
    from server.app.updates.compiling import warm_up_here

    # The kernels loaded now, not on a participant's first update; where numba's cache lacks
    # them, compiled, each by one process of the machine while the others compile other kernels
    # or wait for it and load it.
    try:
        seconds = warm_up_here()
    except Exception:  # an update would meet the same error, and report it for its session
        traceback.print_exc()
    else:
        print(f"update process {os.getpid()} ready in {seconds:.1f} s", file=sys.stderr)


def worker_ready(hold_seconds: float = 0.0) -> int:
    """A job that only starts an update process (its ``worker_init``, which warms it up before
    it takes any job) and names it; held a moment, so that the next goes to another process."""
    time.sleep(hold_seconds)
    return os.getpid()


def apply_records(learner: Any, records: list[Observation]) -> None:
    """Replay what the learner observed, in order."""
    for record in records:
        learner.observe(record)


def run_update(job: dict[str, Any]) -> dict[str, Any]:
    """Restore or build the learner, replay ``records``, update it (unless it is update 0),
    and return its new state, greedy policies and evaluation. ``environment_spec``, when
    given, defines a study's own environment first."""
    from server import domains, learners
    from server.learners.evaluation import normalized_return
    from server.learners.planning import set_planner_threads

    cpu_started = time.process_time()  # this process's, its planner threads' included
    set_planner_threads(job.get("threads", 1))
    spec = job.get("environment_spec")
    if spec is not None and domains.definition(spec.name) != spec:
        # A study's own environment, on a worker that has not registered it (a Dask worker),
        # or that knows another study's environment under the same name.
        if domains.definition(spec.name) is not None:
            domains.unregister(spec.name)
        domains.register_all((spec,))
    env = domains.make(job["environment"])
    if job["base_state"] is not None:
        learner = learners.restore(env, learners.loads(job["base_state"]))
    else:
        learner = learners.make(job["learner"], env, seed=job["seed"], **job["settings"])
    apply_records(learner, job["records"])
    result = learner.update() if job["fit"] else None
    policy = np.stack([learner.greedy_policy(k) for k in range(len(env.tasks))])
    started = time.perf_counter()
    score = normalized_return(env, learner)
    return {
        "learner_state": learners.dumps(learner.state_dict()),
        "greedy_policy": encode(policy),
        "seconds": result.seconds if result else 0.0,
        "objective": result.objective if result else None,
        "steps": result.steps if result else 0,
        "normalized_return": float(score),
        "evaluation_seconds": time.perf_counter() - started,
        "cpu_seconds": time.process_time() - cpu_started,
    }


def records_of(rows: Any) -> list[Observation]:
    """Learner observations from event rows (record, task, state, action, next_state,
    feedback, stay_state); see ``Observed``."""
    records: list[Observation] = []
    for row in rows:
        if row.record == Observed.DEMONSTRATION:
            records.append(DemonstrationStep(row.task, row.state, row.action, row.next_state))
        elif row.record == Observed.AGENT_STEP:
            records.append(AgentStep(row.task, row.state, row.action, row.next_state))
        elif row.record == Observed.IDLE_MOVE:
            records.append(IdleMove(row.state, row.action, row.next_state))
        elif row.record == Observed.FEEDBACK:
            records.append(Feedback(row.feedback))
        if row.stay_state is not None:
            records.append(DemonstrationStep(row.task, row.next_state, STAY, row.stay_state))
    return records
