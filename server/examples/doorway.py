"""Teach BAM and model-based IRL the Doorway environment with a simulated teacher and print the
normalised return after each round: BAM infers where the doorway is from the teacher's
behaviour although the teacher never walks into a wall.

    python -m server.examples.doorway [--rounds 5] [--seed 0]
"""

from __future__ import annotations

import argparse

import numpy as np

from server import domains, learners
from server.learners.evaluation import normalized_return
from server.teacher import Teacher


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if args.rounds < 1:
        parser.error("--rounds must be at least 1")
    env = domains.make("doorway")
    names = ("bam", "model-based", "cloning")
    agents = {name: learners.make(name, env, seed=args.seed) for name in names}
    teacher = Teacher(env, seed=args.seed)
    rng = np.random.default_rng(args.seed)
    print("round  " + "  ".join(f"{learners.DISPLAY_NAMES[n]:>20s}" for n in names))
    print("0      " + "  ".join(f"{normalized_return(env, a):20.1%}" for a in agents.values()))
    for round_ in range(1, args.rounds + 1):
        for task in range(len(env.tasks)):
            demonstration = teacher.demonstration(task, env.sample_start(task, rng))
            for agent in agents.values():
                for state, action, next_state in demonstration:
                    agent.record_demonstration(task, state, action, next_state)
        for agent in agents.values():
            agent.update()
        row = "  ".join(f"{normalized_return(env, a):20.1%}" for a in agents.values())
        print(f"{round_:<7d}{row}", flush=True)
    bam = agents["bam"]
    assert isinstance(bam, learners.BAM)
    fail = env.model.primitives(bam.theta)
    print(
        "BAM's belief that a move fails: doorway (7,5) "
        f"{fail[7 * env.width + 5]:.2f}, walls (7,4) {fail[7 * env.width + 4]:.2f} "
        f"and (7,6) {fail[7 * env.width + 6]:.2f}"
    )


if __name__ == "__main__":
    main()
