"""How BAM's fit behaves for one simulated agent (the diagnosis in docs/reproduction.md).

    python scripts/diagnose_bam.py three-fields 0 [--optimizer lbfgs] [--max-evaluations 400]

Teaches agent AGENT of the demonstrations experiment (the same demonstrations as
`bam-study simulate --seed 0`) for ten rounds, printing after each update the normalised return
and equation (5) at the fitted parameters; then runs further updates on the same data. An
optimiser that has converged leaves the objective where it is; one that oscillates moves it
(and the policy) up and down although nothing new was observed.
"""

from __future__ import annotations

import argparse
import time

from server import domains, learners
from server.learners.objective import OPTIMIZERS
from server.simulation.protocols import Job, demonstration_streams, evaluate, give_demonstrations


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("environment", choices=domains.NAMES)
    parser.add_argument("agent", type=int)
    parser.add_argument("--optimizer", choices=OPTIMIZERS, default="momentum")
    parser.add_argument("--max-evaluations", type=int, help="L-BFGS evaluations per update")
    parser.add_argument("--rounds", type=int, default=10)
    parser.add_argument("--extra-updates", type=int, default=6)
    args = parser.parse_args()

    env = domains.make(args.environment)
    teacher, starts = demonstration_streams(
        Job("demonstrations", args.environment, "bam", args.agent, args.rounds, 0), env
    )
    settings: dict[str, object] = {"optimizer": args.optimizer}
    if args.max_evaluations is not None:
        settings["max_evaluations"] = args.max_evaluations
    bam = learners.make("bam", env, seed=1, **settings)

    def show(label: str, seconds: float | None = None) -> None:
        value, _ = bam.objective()
        took = f"  ({seconds:.2f} s)" if seconds is not None else ""
        print(f"{label:<18} return {evaluate(env, bam)[0]:.3f}  objective {value:9.2f}{took}")

    for round_ in range(1, args.rounds + 1):
        give_demonstrations(env, teacher, bam, starts)
        started = time.perf_counter()
        bam.update()
        show(f"round {round_}", time.perf_counter() - started)
    for extra in range(1, args.extra_updates + 1):
        bam.update()
        show(f"same data, again {extra}")


if __name__ == "__main__":
    main()
