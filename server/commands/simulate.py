"""``bam-study simulate``: the paper's simulated-teacher experiments (section 4).

    bam-study simulate --experiment demonstrations --out results/demonstrations
    bam-study simulate --experiment feedback --environments wall doorway --agents 5 \\
        --rounds 3 --learner-setting alternations=2 --out /tmp/feedback
    bam-study simulate --experiment global-cost --scheduler tcp://scheduler:8786 --out ...

Started again with the same arguments, a run continues where it stopped.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from contextlib import nullcontext
from pathlib import Path

from server.learners.compile_notice import compile_notice
from server.simulation.config import EXPERIMENTS, ConfigError, RunConfig

PROG = "bam-study simulate"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = (
        "experiments: "
        + "; ".join(f"{name} ({', '.join(names)})" for name, names in EXPERIMENTS.items())
        + ".\nenvironments: by default the paper's eight; an unknown name lists the valid ones."
        "\nwrites curves.csv, summary.csv, EXPERIMENT.png/.svg and report.md in --out; run.json "
        "and jobs.jsonl let an interrupted run resume."
    )
    parser.add_argument("--experiment", required=True, choices=tuple(EXPERIMENTS))
    parser.add_argument(
        "--environments", nargs="+", metavar="NAME", help="default: all eight environments"
    )
    parser.add_argument(
        "--learners", nargs="+", metavar="NAME", help="default: the experiment's three learners"
    )
    parser.add_argument(
        "--agents", type=int, default=50, help="agents per environment and learner (default 50)"
    )
    parser.add_argument("--rounds", type=int, default=10, help="rounds of teaching (default 10)")
    parser.add_argument(
        "--jobs",
        type=int,
        default=None,
        help="local worker processes (default: all cores); with fewer processes than cores, "
        "each splits its planner passes over the cores left (same numbers)",
    )
    parser.add_argument(
        "--seed", type=int, default=0, help="the seed of every random stream (default 0)"
    )
    parser.add_argument(
        "--learner-setting",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="override a learner setting for every learner that has it (repeatable), "
        "e.g. alternations=2",
    )
    parser.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="run the jobs on this Dask distributed scheduler instead of the local pool "
        "(needs bam-study[dask] here and bam-study installed on the workers)",
    )
    parser.add_argument(
        "--study",
        type=Path,
        metavar="STUDY.toml",
        help="a study file whose own environments ([environments.NAME]) are simulated; "
        "--environments then defaults to them",
    )
    parser.add_argument("--out", required=True, type=Path, metavar="DIR", help="output folder")
    parser.add_argument(
        "--minari",
        type=Path,
        metavar="DIR",
        help="also write the simulated teacher's demonstrations as Minari datasets, one per "
        "environment, in this new folder (for offline RL baselines on the paper's protocol)",
    )


def count(number: int, noun: str) -> str:
    return f"{number} {noun}{'' if number == 1 else 's'}"


def command_line(args: argparse.Namespace, config: RunConfig) -> str:
    """The command that reproduces the run (and resumes it), for the report."""
    words = [
        "bam-study",
        "simulate",
        "--experiment",
        config.experiment,
        "--environments",
        *config.environments,
        "--learners",
        *config.learners,
        "--agents",
        str(config.agents),
        "--rounds",
        str(config.rounds),
        "--seed",
        str(config.seed),
    ]
    for assignment in args.learner_setting:
        words += ["--learner-setting", assignment]
    if args.scheduler:
        words += ["--scheduler", args.scheduler]
    if getattr(args, "study", None) is not None:
        words += ["--study", str(args.study)]
    words += ["--out", str(args.out)]
    return " ".join(shlex.quote(word) for word in words)


def run(args: argparse.Namespace) -> int:
    from server.simulation.config import build_config
    from server.simulation.outputs import write_outputs
    from server.simulation.runner import (
        Backend,
        DaskBackend,
        LocalBackend,
        SimulationError,
        check_out_dir,
        default_workers,
        run_jobs,
    )

    backend: Backend | None = None
    try:
        environments = args.environments
        if args.study is not None:
            from server.commands.studies import StudyEnvironmentsError, register_study

            try:
                own = register_study(args.study)
            except StudyEnvironmentsError as error:
                raise ConfigError(str(error)) from None
            if args.scheduler:
                raise ConfigError("--study runs on the local pool: a cluster's workers "
                                  "do not know the study's environments")  # fmt: skip
            environments = environments or list(own)
        config, notes = build_config(
            args.experiment,
            environments,
            args.learners,
            args.agents,
            args.rounds,
            args.seed,
            args.learner_setting,
        )
        workers = default_workers() if args.jobs is None else args.jobs
        if workers < 1:
            raise ConfigError(f"--jobs must be at least 1, got {workers}")
        check_out_dir(args.out, config)
        if args.minari is not None and args.minari.exists():
            raise ConfigError(f"--minari {args.minari} already exists: give a new folder")
        backend = DaskBackend(args.scheduler) if args.scheduler else LocalBackend(workers)
    except ConfigError as error:
        print(f"bam-study simulate: error: {error}", file=sys.stderr)
        return 2
    if args.scheduler and args.jobs is not None:
        notes.append("--jobs is ignored with --scheduler: the cluster's workers run the jobs")
    for note in notes:
        print(f"bam-study simulate: note: {note}", file=sys.stderr)
    try:
        jobs = config.agents * len(config.environments) * len(config.learners)
        print(
            f"{config.experiment}: {jobs} jobs ({count(len(config.environments), 'environment')}"
            f" x {count(len(config.learners), 'learner')} x {count(config.agents, 'agent')}, "
            f"{count(config.rounds, 'round')} each) on {backend.describe()}",
            file=sys.stderr,
        )
        # A cluster's workers have caches of their own.
        notice = (
            nullcontext() if args.scheduler else compile_notice(sys.stderr, PROG, "the first jobs")
        )
        with notice:
            outcome = run_jobs(config, args.out, backend)
    except KeyboardInterrupt:
        print(
            f"bam-study simulate: stopped; finished jobs are kept in {args.out}: run the same "
            "command again to continue",
            file=sys.stderr,
        )
        raise
    except ConfigError as error:
        print(f"bam-study simulate: error: {error}", file=sys.stderr)
        return 2
    except SimulationError as error:
        print(f"bam-study simulate: error: {error}", file=sys.stderr)
        return 1
    finally:
        backend.close()
    written = write_outputs(
        args.out, config, outcome.results, outcome.sessions, command_line(args, config)
    )
    print(f"wrote {', '.join(str(path) for path in written)}", file=sys.stderr)
    if args.minari is not None:
        from server.rl.teacher_datasets import write_teacher_datasets

        ids = write_teacher_datasets(
            config.environments, config.agents, config.rounds, config.seed, args.minari
        )
        print(f"wrote the Minari datasets {', '.join(ids)} in {args.minari}", file=sys.stderr)
    return 0
