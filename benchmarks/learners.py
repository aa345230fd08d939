"""Learner speed benchmark: per environment and learner, the update time (median and
p95) after 1, 5 and 10 rounds of simulated demonstrations, one planner forward pass, one
forward-plus-backward pass, and the learner state's serialised size.

    python benchmarks/learners.py [--environments doorway flip] [--learners bam] [--repeats 5]
                                  [--clock cpu] [--breakdown]

Each timed update restarts from the same saved learner state, so the repeats measure the same
update; the planner passes are timed at least 50 times each. ``--clock cpu`` times the
process's CPU time instead of the wall clock (on a machine shared with other work, the wall
clock counts their turns too). ``--breakdown`` adds, per environment and learner, where the
update after 10 rounds spends its time: the planner passes it runs (forward and reverse) and
their time (compiled cost steps, ``compiled_steps``, and compiled dynamics steps,
``compiled_dynamics_steps``, count whole there: their passes and the likelihood and steps
between them), the rest (the likelihoods, the optimiser steps, the model's table and its
pull-back), a forward pass's nanoseconds per backup and what NumPy's vectorised exp costs per
number on the same CPU, all in the passes' precision (``--setting planner_precision=float64``:
double). ``--versus NAME=VALUE`` adds the update after 10 rounds timed alternately at the
settings and with that setting changed, from the same saved state, and their ratio: the way to
compare two settings on a machine whose speed drifts (``--versus planner_precision=float64``).

Targets (2-core machine, one planner thread, update after 10 rounds, median): BAM <= 100 ms
and model-based IRL <= 50 ms on every environment; forward+backward <= 4x forward; learner
state < 5 MB.
"""

from __future__ import annotations

import argparse
import functools
import inspect
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
from server.learners import NAMES, _kernels, dumps, make, planning, restore
from server.learners.planning import TransitionOperator, set_planner_threads, soft_plan
from server.learners.settings import PlannerSettings
from server.simulation.config import ConfigError, parse_learner_settings
from server.teacher import Teacher

CHECKPOINTS = (1, 5, 10)
# Where compiled cost steps (_kernels.cost_steps_tasks) are told how many steps to take.
COST_STEPS_ARGUMENT = list(inspect.signature(_kernels.cost_steps_tasks.py_func).parameters).index(
    "steps"
)
PLANNER_REPEATS = 50
CLOCKS = {"wall": time.perf_counter, "cpu": time.process_time}
clock = time.perf_counter


def time_update(env, learner, repeats: int) -> tuple[float, float]:
    state = learner.state_dict()
    seconds = []
    for _ in range(repeats):
        copy = restore(env, state)
        started = clock()
        copy.update()
        seconds.append(clock() - started)
    seconds.sort()
    p95 = seconds[min(len(seconds) - 1, int(np.ceil(0.95 * len(seconds))) - 1)]
    return statistics.median(seconds), p95


def time_planner(env, repeats: int, precision: str = "float64") -> tuple[float, float]:
    operator = TransitionOperator.build(env.model.transitions(env.model.initial_parameters()))
    rewards = np.random.default_rng(0).normal(size=(len(env.tasks), env.num_states))
    d_q = np.ones((len(env.tasks), env.num_states, env.num_actions))
    plan = functools.partial(soft_plan, operator, rewards, 1.0, env.horizon, precision=precision)
    plan().backward(d_q)  # compile / warm up
    forward, both = [], []
    for _ in range(repeats):
        started = clock()
        plan(keep_trace=False)
        forward.append(clock() - started)
        started = clock()
        plan().backward(d_q)
        both.append(clock() - started)
    return statistics.median(forward), statistics.median(both)


def backups(env) -> int:
    """Log-sum-exp backups of one forward pass over every state and task: S x A x
    (horizon - 1) x tasks (the last backup's value is never taken)."""
    return env.num_states * env.num_actions * (env.horizon - 1) * len(env.tasks)


def exp_seconds(count: int, repeats: int, precision: str = "float64") -> float:
    """NumPy's exp of ``count`` non-positive numbers (a pass's exponents) in the passes'
    precision, median."""
    x = (-np.random.default_rng(0).random(count) * 20.0).astype(precision)
    out = np.empty_like(x)
    seconds = []
    for _ in range(repeats):
        started = clock()
        np.exp(x, out=out)
        seconds.append(clock() - started)
    return statistics.median(seconds)


def pass_breakdown(env, learner, repeats: int) -> tuple[int, int, float, float]:
    """One update of ``learner`` (from its saved state, ``repeats`` times): its forward and
    reverse planner passes, and the median seconds in the passes and in the whole update."""
    real = planning.run_pass
    counts = {"forward": 0, "reverse": 0}
    in_passes = [0.0]

    def counted(chunks, kernel, kernel_chunks, arguments):  # type: ignore[no-untyped-def]
        if kernel is _kernels.cost_steps_tasks:  # compiled cost steps: a pass of each a step
            steps = arguments[COST_STEPS_ARGUMENT]
            counts["forward"] += steps
            counts["reverse"] += steps
        else:
            counts["forward" if kernel is _kernels.soft_forward_tasks else "reverse"] += 1
        started = clock()
        real(chunks, kernel, kernel_chunks, arguments)
        in_passes[0] += clock() - started

    # Compiled dynamics steps: a teacher gradient is a forward and a reverse pass, the loop
    # of them one of each a step it took; counted whole with the likelihood and steps between.
    real_kernels = {
        "teacher_gradient": (_kernels.teacher_gradient, lambda result: 1),
        "dynamics_steps": (_kernels.dynamics_steps, lambda result: int(result[4])),
    }

    def counted_kernel(name):  # type: ignore[no-untyped-def]
        kernel, passes_of = real_kernels[name]

        def run(*arguments):  # type: ignore[no-untyped-def]
            started = clock()
            result = kernel(*arguments)
            in_passes[0] += clock() - started
            counts["forward"] += passes_of(result)
            counts["reverse"] += passes_of(result)
            return result

        return run

    state = learner.state_dict()
    passes, whole = [], []
    planning.run_pass = counted
    for name in real_kernels:
        setattr(_kernels, name, counted_kernel(name))
    try:
        for _ in range(repeats):
            counts.update(forward=0, reverse=0)
            in_passes[0] = 0.0
            copy = restore(env, state)
            started = clock()
            copy.update()
            whole.append(clock() - started)
            passes.append(in_passes[0])
    finally:
        planning.run_pass = real
        for name, (kernel, _) in real_kernels.items():
            setattr(_kernels, name, kernel)
    return counts["forward"], counts["reverse"], statistics.median(passes), statistics.median(whole)


def time_versus(env, learner, other: dict, repeats: int) -> tuple[float, float]:
    """The update after 10 rounds of ``learner`` and of the same saved state with the settings
    ``other`` (from the same data and parameters), timed alternately ``repeats`` times each so
    that both meet the same drifts of the machine: the median seconds of each."""
    state = learner.state_dict()
    changed = {**state, "settings": {**state["settings"], **other}}
    restore(env, changed).update()  # compile / warm up
    seconds: tuple[list[float], list[float]] = ([], [])
    for _ in range(repeats):
        for times, saved in zip(seconds, (state, changed), strict=True):
            copy = restore(env, saved)
            started = clock()
            copy.update()
            times.append(clock() - started)
    return statistics.median(seconds[0]), statistics.median(seconds[1])


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
    parser.add_argument(
        "--clock",
        choices=sorted(CLOCKS),
        default="wall",
        help="wall: elapsed time (default); cpu: the process's CPU time",
    )
    parser.add_argument(
        "--versus",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="also time the update after 10 rounds with this setting changed, alternately "
        "with the update at the other settings (a third table; repeatable)",
    )
    parser.add_argument(
        "--breakdown",
        action="store_true",
        help="also where the update after 10 rounds spends its time (a second table)",
    )
    args = parser.parse_args(argv)
    if args.threads < 1:
        parser.error("--threads must be at least 1")
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    global clock
    clock = CLOCKS[args.clock]
    set_planner_threads(args.threads)
    print(f"planner threads: {args.threads}, clock: {args.clock}")
    try:  # each value of the type of the learner's default (true/false, numbers, text)
        settings_of, _ = parse_learner_settings(args.setting, args.learners)
        versus_of, _ = parse_learner_settings(args.versus, args.learners)
    except ConfigError as error:
        parser.error(str(error))
    precision = next(
        (str(s["planner_precision"]) for s in settings_of.values() if "planner_precision" in s),
        PlannerSettings.field("planner_precision").default,
    )
    header = (
        f"{'environment':13s} {'learner':12s} "
        + " ".join(f"{'upd@' + str(r) + ' med/p95 ms':>19s}" for r in CHECKPOINTS)
        + f" {'fwd ms':>7s} {'fwd+bwd ms':>10s} {'ratio':>5s} {'state KB':>8s}"
    )
    print(header)
    print("-" * len(header))
    breakdown = []
    versus_rows = []
    for env_name in args.environments:
        env = domains.make(env_name)
        # A pass takes a millisecond or so: many of them, or a burst of the machine's noise
        # decides the median (flip's ratio read 4.0 in one run of 5, 2.6 in runs of 50).
        forward, both = time_planner(env, max(args.repeats, PLANNER_REPEATS), precision)
        for learner_name in args.learners:
            learner = make(learner_name, env, seed=args.seed, **settings_of.get(learner_name, {}))
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
                if args.versus and round_ == max(CHECKPOINTS):
                    other = versus_of.get(learner_name, {})
                    versus_rows.append(
                        (env_name, learner_name, *time_versus(env, learner, other, args.repeats))
                    )
                if args.breakdown and round_ == max(CHECKPOINTS):
                    count = backups(env)
                    breakdown.append(
                        (
                            env_name,
                            learner_name,
                            *pass_breakdown(env, learner, args.repeats),
                            forward / count,
                            exp_seconds(count, max(args.repeats, PLANNER_REPEATS), precision)
                            / count,
                        )
                    )
                learner.update()
            size = len(dumps(learner.state_dict()))
            print(
                f"{env_name:13s} {learner_name:12s} "
                + " ".join(f"{c:>19s}" for c in cells)
                + f" {forward * 1e3:7.2f} {both * 1e3:10.2f} {both / forward:5.1f} {size / 1024:8.1f}",
                flush=True,
            )
    if breakdown:
        print_breakdown(breakdown)
    if versus_rows:
        print_versus(versus_rows, " ".join(args.versus))
    return 0


def print_versus(rows: list[tuple], changed: str) -> None:
    header = (
        f"{'environment':13s} {'learner':12s} {'upd@10 ms':>10s} {'with ' + changed:>28s} "
        f"{'ratio':>6s}"
    )
    print()
    print(header)
    print("-" * len(header))
    for env_name, learner_name, before, after in rows:
        print(
            f"{env_name:13s} {learner_name:12s} {before * 1e3:10.0f} {after * 1e3:28.0f} "
            f"{after / before:6.2f}",
            flush=True,
        )


def print_breakdown(rows: list[tuple]) -> None:
    header = (
        f"{'environment':13s} {'learner':12s} {'passes fwd/rev':>14s} {'update ms':>9s} "
        f"{'in passes ms':>12s} {'rest ms':>7s} {'ns/backup':>9s} {'exp ns':>6s}"
    )
    print()
    print(header)
    print("-" * len(header))
    for env_name, learner_name, forward, reverse, passes, whole, per_backup, per_exp in rows:
        print(
            f"{env_name:13s} {learner_name:12s} {f'{forward}/{reverse}':>14s} "
            f"{whole * 1e3:9.0f} {passes * 1e3:12.0f} {(whole - passes) * 1e3:7.0f} "
            f"{per_backup * 1e9:9.2f} {per_exp * 1e9:6.2f}"
        )


if __name__ == "__main__":
    sys.exit(main())
