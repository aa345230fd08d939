"""Simulation speed benchmark: time the demonstrations experiment, or a stated
fraction of it, and project the full-size run (8 environments x 3 learners x 50 agents x 10
rounds; target on a 2-core machine: at most 15 minutes).

    python benchmarks/simulate.py                                   # the full experiment
    python benchmarks/simulate.py --environments wall flip --agents 4 --rounds 10 --jobs 2
    python benchmarks/simulate.py --agents 2 --learner-setting optimizer=lbfgs

The jobs run exactly as ``bam-study simulate`` runs them (same runner, fresh temporary
folder). The table gives, per environment and learner, the measured compute time per agent,
the share of it spent in learner updates, and the projected compute time of 50 agents and 10
rounds. When fewer than 10 rounds are timed, the time of the missing rounds is extrapolated
with a straight line through the measured per-round times (data grows every round, so a round
costs more than the one before); the projection of the wall time assumes the parallel
efficiency measured here.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

# Run as a script, this folder comes first on sys.path, and benchmarks/server.py would
# shadow the ``server`` package.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import numpy as np

from server import domains
from server.simulation.config import ConfigError, build_config
from server.simulation.runner import LocalBackend, default_workers, run_jobs

FULL_AGENTS = 50
FULL_ROUNDS = 10
TARGET_SECONDS = 15 * 60


def per_round_seconds(rows: list[dict], seconds: float) -> np.ndarray:
    """Each round's cost in one job: its update time, plus the job's other time (teacher,
    evaluation) spread evenly over the rounds."""
    updates = np.array([row["update_seconds"] for row in rows if row["round"] > 0])
    other = max(0.0, seconds - float(updates.sum()))
    return updates + other / max(1, len(updates))


def projected_job_seconds(rounds: np.ndarray) -> float:
    """The compute time of one job of ``FULL_ROUNDS`` rounds from measured per-round times."""
    measured = len(rounds)
    if measured >= FULL_ROUNDS:
        return float(rounds[:FULL_ROUNDS].sum())
    if measured >= 2:
        slope, intercept = np.polyfit(np.arange(1, measured + 1), rounds, 1)
        missing = np.arange(measured + 1, FULL_ROUNDS + 1)
        extra = np.maximum(intercept + slope * missing, rounds[-1])
    else:
        extra = np.full(FULL_ROUNDS - measured, rounds[-1])  # a lower bound
    return float(rounds.sum() + extra.sum())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--experiment", default="demonstrations")
    parser.add_argument("--environments", nargs="+", default=list(domains.ENVIRONMENTS))
    parser.add_argument("--learners", nargs="+", default=None)
    parser.add_argument("--agents", type=int, default=FULL_AGENTS)
    parser.add_argument("--rounds", type=int, default=FULL_ROUNDS)
    parser.add_argument("--jobs", type=int, default=default_workers())
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--learner-setting", action="append", default=[], metavar="NAME=VALUE")
    args = parser.parse_args(argv)
    try:
        config, notes = build_config(
            args.experiment,
            args.environments,
            args.learners,
            args.agents,
            args.rounds,
            args.seed,
            args.learner_setting,
        )
        backend = LocalBackend(args.jobs)
    except ConfigError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    for note in notes:
        print(f"note: {note}", file=sys.stderr)

    with tempfile.TemporaryDirectory(prefix="bam-simulate-benchmark-") as folder:
        started = time.perf_counter()
        outcome = run_jobs(config, Path(folder) / "run", backend)
        wall = time.perf_counter() - started

    compute = sum(result.seconds for result in outcome.results)
    updates = sum(result.update_seconds for result in outcome.results)
    # Measured parallel efficiency, assumed for the projections (1 when run on one worker).
    efficiency = compute / (wall * args.jobs) if wall > 0 else 1.0

    header = (
        f"{'environment':13s} {'learner':12s} {'s/agent':>8s} {'update %':>8s} "
        f"{'projected s (' + str(FULL_AGENTS) + ' agents x ' + str(FULL_ROUNDS) + ' rounds)':>36s}"
    )
    print(
        f"{config.experiment}: {len(config.environments)} environment(s) x "
        f"{len(config.learners)} learner(s) x {config.agents} agent(s) x {config.rounds} "
        f"round(s) on {backend.describe()}"
    )
    print(header)
    print("-" * len(header))
    projected_compute = 0.0
    for environment in config.environments:
        for learner in config.learners:
            results = [
                r
                for r in outcome.results
                if r.rows[0]["environment"] == environment and r.rows[0]["learner"] == learner
            ]
            seconds = statistics.mean(r.seconds for r in results)
            share = sum(r.update_seconds for r in results) / sum(r.seconds for r in results)
            per_job = statistics.mean(
                projected_job_seconds(per_round_seconds(r.rows, r.seconds)) for r in results
            )
            projected_compute += per_job * FULL_AGENTS
            print(
                f"{environment:13s} {learner:12s} {seconds:8.2f} {100 * share:8.1f} "
                f"{per_job * FULL_AGENTS:36.0f}"
            )
    print("-" * len(header))
    print(f"wall time                 {wall:10.1f} s")
    print(f"compute time (all jobs)   {compute:10.1f} s  (parallel efficiency {efficiency:.2f})")
    print(f"of which learner updates  {updates:10.1f} s  ({100 * updates / compute:.1f}%)")
    missing = [name for name in domains.ENVIRONMENTS if name not in config.environments]
    scope = "full size" if not missing else f"without {', '.join(missing)}"
    print(f"projected {scope} ({FULL_AGENTS} agents, {FULL_ROUNDS} rounds):")
    print(f"  compute                 {projected_compute:10.0f} s")
    for workers in sorted({args.jobs, 2}):
        projected_wall = projected_compute / (workers * min(1.0, efficiency))
        verdict = ""
        if workers == 2 and not missing:
            verdict = "  meets" if projected_wall <= TARGET_SECONDS else "  misses"
            verdict += f" the {TARGET_SECONDS // 60}-minute target for 2 cores"
        print(
            f"  wall on {workers} worker(s)     {projected_wall:10.0f} s = "
            f"{projected_wall / 60:.1f} min{verdict}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
