"""Learner speed benchmark: per environment and learner, the update time (median and
p95) after 1, 5 and 10 rounds of simulated demonstrations, one planner forward pass, one
forward-plus-backward pass, and the learner state's serialised size.

    python benchmarks/learners.py [--environments doorway flip] [--learners bam] [--repeats 5]

Each timed update restarts from the same saved learner state, so the repeats measure the same
update; the planner passes are timed at least 50 times each. Targets (2-core machine): BAM
update after 10 rounds <= 250 ms median on every environment; forward+backward <= 4x forward;
learner state < 5 MB.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

# Run as a script, this folder comes first on sys.path, and benchmarks/server.py would
# shadow the ``server`` package.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import numpy as np

from server import domains
from server.cores import available_cores
from server.learners import NAMES, dumps, make, restore
from server.learners.planning import TransitionOperator, set_planner_threads, soft_plan
from server.teacher import Teacher

CHECKPOINTS = (1, 5, 10)
PLANNER_REPEATS = 50


def time_update(env, learner, repeats: int) -> tuple[float, float]:
    state = learner.state_dict()
    seconds = []
    for _ in range(repeats):
        copy = restore(env, state)
        started = time.perf_counter()
        copy.update()
        seconds.append(time.perf_counter() - started)
    seconds.sort()
    p95 = seconds[min(len(seconds) - 1, int(np.ceil(0.95 * len(seconds))) - 1)]
    return statistics.median(seconds), p95


def time_planner(env, repeats: int) -> tuple[float, float]:
    operator = TransitionOperator.build(env.model.transitions(env.model.initial_parameters()))
    rewards = np.random.default_rng(0).normal(size=(len(env.tasks), env.num_states))
    d_q = np.ones((len(env.tasks), env.num_states, env.num_actions))
    soft_plan(operator, rewards, 1.0, env.horizon).backward(d_q)  # compile / warm up
    forward, both = [], []
    for _ in range(repeats):
        started = time.perf_counter()
        soft_plan(operator, rewards, 1.0, env.horizon, keep_trace=False)
        forward.append(time.perf_counter() - started)
        started = time.perf_counter()
        soft_plan(operator, rewards, 1.0, env.horizon).backward(d_q)
        both.append(time.perf_counter() - started)
    return statistics.median(forward), statistics.median(both)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--environments", nargs="+", choices=domains.NAMES, default=list(domains.ENVIRONMENTS)
    )
    parser.add_argument("--learners", nargs="+", choices=NAMES, default=list(NAMES))
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--threads",
        type=int,
        default=available_cores(),
        help="planner threads, as a study server's update process has them "
        "(default: the number of cores)",
    )
    parser.add_argument(
        "--setting",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="learner setting override, e.g. optimizer=lbfgs (repeatable)",
    )
    args = parser.parse_args(argv)
    if args.threads < 1:
        parser.error("--threads must be at least 1")
    set_planner_threads(args.threads)
    print(f"planner threads: {args.threads}")
    settings = {}
    for item in args.setting:
        name, _, value = item.partition("=")
        try:
            settings[name] = int(value)
        except ValueError:
            try:
                settings[name] = float(value)
            except ValueError:
                settings[name] = value
    header = (
        f"{'environment':13s} {'learner':12s} "
        + " ".join(f"{'upd@' + str(r) + ' med/p95 ms':>19s}" for r in CHECKPOINTS)
        + f" {'fwd ms':>7s} {'fwd+bwd ms':>10s} {'ratio':>5s} {'state KB':>8s}"
    )
    print(header)
    print("-" * len(header))
    for env_name in args.environments:
        env = domains.make(env_name)
        # A pass takes a millisecond or so: many of them, or a burst of the machine's noise
        # decides the median (flip's ratio read 4.0 in one run of 5, 2.6 in runs of 50).
        forward, both = time_planner(env, max(args.repeats, PLANNER_REPEATS))
        for learner_name in args.learners:
            applicable = {
                k: v for k, v in settings.items() if k in make(learner_name, env).settings
            }
            learner = make(learner_name, env, seed=args.seed, **applicable)
            teacher = Teacher(env, seed=args.seed)
            rng = np.random.default_rng(args.seed)
            cells = []
            for round_ in range(1, max(CHECKPOINTS) + 1):
                for task in range(len(env.tasks)):
                    for step in teacher.demonstration(task, env.sample_start(task, rng)):
                        learner.record_demonstration(task, *step)
                if round_ in CHECKPOINTS:
                    median, p95 = time_update(env, learner, args.repeats)
                    cells.append(f"{median * 1e3:9.0f}/{p95 * 1e3:<9.0f}")
                learner.update()
            size = len(dumps(learner.state_dict()))
            print(
                f"{env_name:13s} {learner_name:12s} "
                + " ".join(f"{c:>19s}" for c in cells)
                + f" {forward * 1e3:7.2f} {both * 1e3:10.2f} {both / forward:5.1f} {size / 1024:8.1f}",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
