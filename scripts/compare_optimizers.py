"""Optimiser settings against the reference schedule, on the paper's simulated teacher.

    python scripts/compare_optimizers.py --environments doorway flip --agents 5 \
        --variant warm=optimizer=warm-lbfgs,warm_alternations=2

Teaches each agent of the demonstrations experiment (the same demonstrations as
`bam-study simulate --seed S`, agents 0 .. AGENTS-1) once with the learner's default settings
(the paper authors' reference schedule) and once with each variant, and prints per environment
and variant: the normalised return (percent of optimal, mean over agents) averaged over the
rounds and at the last round; the value of equation (5) after each update minus the reference's
on the same data, averaged over the updates after the first (a first fit is the reference
schedule in every `warm-lbfgs` variant); the share of those updates where the variant ends at
least as high as the reference; and the median time of those updates. This is the measure the
reference settings ask of a faster optimiser: the same or a better likelihood.
"""

from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from server import domains, learners
from server.simulation.config import ConfigError, parse_learner_settings
from server.simulation.protocols import (
    Job,
    agent_streams,
    demonstration_streams,
    evaluate,
    give_demonstrations,
)

REFERENCE = "reference"


@dataclass(frozen=True)
class Variant:
    name: str
    settings: tuple[tuple[str, Any], ...]


REFERENCE_VARIANT = Variant(REFERENCE, ())  # the learner's default settings


def parse_variant(text: str, learner: str) -> Variant:
    """NAME=SETTING=VALUE[,SETTING=VALUE...] -> a variant of the learner's settings."""
    name, sep, assignments = text.partition("=")
    if not sep or not name.strip() or not assignments.strip():
        raise ConfigError(f"--variant expects NAME=SETTING=VALUE[,SETTING=VALUE...], got {text!r}")
    if name.strip() == REFERENCE:
        raise ConfigError(f"--variant: {REFERENCE!r} names the default settings, choose another")
    per_learner, notes = parse_learner_settings(assignments.split(","), [learner])
    if notes:
        raise ConfigError(f"--variant {name}: {notes[0]}")
    settings = per_learner.get(learner, {})
    learners.make(learner, domains.make("wall"), **settings)  # refuses bad values here
    return Variant(name.strip(), tuple(sorted(settings.items())))


def run_agent(
    environment: str, learner: str, agent: int, rounds: int, seed: int, variant: Variant
) -> tuple[str, str, int, np.ndarray]:
    """Rows (round, normalised return, equation (5) after the update, update seconds)."""
    job = Job("demonstrations", environment, learner, agent, rounds, seed, variant.settings)
    env = domains.make(environment)
    teacher, starts = demonstration_streams(job, env)
    taught, _, _ = agent_streams(job, env)
    rows = []
    for round_ in range(1, rounds + 1):
        give_demonstrations(env, teacher, taught, starts)
        started = time.perf_counter()
        taught.update()
        seconds = time.perf_counter() - started
        value, _ = taught.objective()  # type: ignore[attr-defined]
        rows.append((round_, evaluate(env, taught)[0], value, seconds))
    return environment, variant.name, agent, np.array(rows)


def table(results: list[tuple[str, str, int, np.ndarray]], variants: list[Variant]) -> str:
    runs = {(env, name, agent): rows for env, name, agent, rows in results}
    environments = [e for e in domains.NAMES if any(key[0] == e for key in runs)]
    header = (
        f"{'environment':<20}{'variant':<12}{'return %':>9}{'last %':>8}"
        f"{'eq.5 - ref':>12}{'>= ref':>8}{'update s':>10}"
    )
    lines = [header, "-" * len(header)]
    for env in environments:
        agents = sorted({key[2] for key in runs if key[0] == env})
        for variant in [REFERENCE_VARIANT, *variants]:
            mine = [runs[(env, variant.name, a)] for a in agents]
            ref = [runs[(env, REFERENCE, a)] for a in agents]
            later = np.concatenate([m[1:, 2] - r[1:, 2] for m, r in zip(mine, ref, strict=True)])
            seconds = np.concatenate([m[1:, 3] for m in mine])
            lines.append(
                f"{env:<20}{variant.name:<12}"
                f"{100 * np.mean([m[:, 1].mean() for m in mine]):>9.1f}"
                f"{100 * np.mean([m[-1, 1] for m in mine]):>8.1f}"
                f"{later.mean() if later.size else float('nan'):>12.2f}"
                f"{(later >= 0).mean() if later.size else float('nan'):>8.2f}"
                f"{np.median(seconds) if seconds.size else float('nan'):>10.3f}"
            )
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog="Each variant runs as many updates as the reference; the time is wall time.",
    )
    parser.add_argument(
        "--environments",
        nargs="+",
        default=list(domains.ENVIRONMENTS),
        choices=domains.NAMES,
        help="default: the paper's eight",
    )
    parser.add_argument("--learner", default="bam", choices=["bam", "model-based", "global-cost"])
    parser.add_argument("--agents", type=int, default=5)
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    parser.add_argument(
        "--variant",
        action="append",
        required=True,
        metavar="NAME=SETTING=VALUE[,SETTING=VALUE...]",
        help="settings to compare with the reference (repeatable)",
    )
    args = parser.parse_args(argv)
    for flag in ("agents", "rounds", "jobs"):
        if getattr(args, flag) < 1:
            parser.error(f"--{flag} must be at least 1")
    try:
        variants = [parse_variant(text, args.learner) for text in args.variant]
    except (ConfigError, ValueError) as error:
        parser.error(str(error))
    if len({v.name for v in variants}) != len(variants):
        parser.error("--variant names must differ")
    work = [
        (env, args.learner, agent, args.rounds, args.seed, variant)
        for env in args.environments
        for agent in range(args.agents)
        for variant in [REFERENCE_VARIANT, *variants]
    ]
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        results = list(pool.map(run_agent, *zip(*work, strict=True)))
    print(
        f"{args.learner}, demonstrations, {args.agents} agents x {args.rounds} rounds, "
        f"seed {args.seed}; eq.5 - ref and >= ref over updates 2-{args.rounds}"
    )
    print(table(results, variants))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
