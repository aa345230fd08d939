"""Learner update speed of this checkout against an earlier commit, on the same machine:
2-core virtual machines differ by up to 3x in speed from one day to the next and are noisy
within a run, so a figure is only comparable with one measured beside it.

    python benchmarks/compare.py --against 2bb2b4e [--environments flip doorway] [--cycles 3]

Learner states after ``--rounds - 1`` updates of simulated demonstrations are built once, with
this checkout, and saved; the earlier commit is checked out into a temporary git worktree.
Each cycle then times ``--repeats`` updates of every saved learner in a fresh process of each
version, one version after the other, so that both meet the same drifts of the machine. The
table gives per environment the fastest and the median update of each version, and the ratio
of the fastest (after / before; below 1 is faster). The saved states are the same bytes for
both, so the two versions do exactly the same update.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

# Run as a script, this folder comes first on sys.path, and benchmarks/server.py would
# shadow the ``server`` package.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import numpy as np

from server import domains
from server.learners import NAMES, dumps, make
from server.teacher import Teacher

ROOT = Path(__file__).resolve().parents[1]

# Run by each version with its own tree first on sys.path: restore each saved learner (without
# the settings that version does not have yet: it does what it did before them), one warm-up
# update (compilation), then the timed ones.
TIMER = """
import json, sys, time
from pathlib import Path
import server
from server import domains
from server.learners import learner_class, loads, restore
if not Path(server.__file__).resolve().is_relative_to(Path.cwd().resolve()):
    sys.exit(f"imported {server.__file__}, not the version in {Path.cwd()}")
states, repeats = Path(sys.argv[1]), int(sys.argv[2])
out = {}
for path in sorted(states.glob("*.npz")):
    env = domains.make(path.stem.split("--")[0])
    state = loads(path.read_bytes())
    known = learner_class(str(state["learner"])).default_settings
    state["settings"] = {k: v for k, v in state["settings"].items() if k in known}
    restore(env, state).update()
    seconds = []
    for _ in range(repeats):
        learner = restore(env, state)
        started = time.perf_counter()
        learner.update()
        seconds.append(time.perf_counter() - started)
    out[path.stem] = seconds
print(json.dumps(out))
"""


def save_states(folder: Path, environments: list[str], learner: str, rounds: int) -> None:
    for name in environments:
        env = domains.make(name)
        agent = make(learner, env, seed=0)
        teacher = Teacher(env, seed=0)
        rng = np.random.default_rng(0)
        for round_ in range(1, rounds + 1):
            for task in range(len(env.tasks)):
                for step in teacher.demonstration(task, env.sample_start(task, rng)):
                    agent.record_demonstration(task, *step)
            if round_ < rounds:
                agent.update()
        (folder / f"{name}--{learner}.npz").write_bytes(dumps(agent.state_dict()))


def time_version(tree: Path, states: Path, repeats: int) -> dict[str, list[float]]:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    result = subprocess.run(
        [sys.executable, "-c", TIMER, str(states), str(repeats)],
        cwd=tree,
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    if result.returncode != 0:
        raise SystemExit(f"timing in {tree} failed:\n{result.stderr.strip()}")
    return json.loads(result.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--against", required=True, metavar="REV", help="the earlier commit")
    parser.add_argument(
        "--environments", nargs="+", choices=domains.NAMES, default=list(domains.ENVIRONMENTS)
    )
    parser.add_argument("--learner", choices=NAMES, default="bam")
    parser.add_argument("--rounds", type=int, default=10, help="rounds of data (default 10)")
    parser.add_argument("--repeats", type=int, default=2, help="updates per process")
    parser.add_argument("--cycles", type=int, default=3, help="processes of each version")
    args = parser.parse_args(argv)
    for name in ("rounds", "repeats", "cycles"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be at least 1")
    revision = subprocess.run(
        ["git", "rev-parse", "--verify", "--quiet", f"{args.against}^{{commit}}"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=False,
    )
    if revision.returncode != 0:
        parser.error(f"--against: {args.against!r} is not a commit of {ROOT}")
    commit = revision.stdout.strip()
    with tempfile.TemporaryDirectory(prefix="bam-compare-") as temporary:
        folder = Path(temporary)
        states, before = folder / "states", folder / "before"
        states.mkdir()
        save_states(states, args.environments, args.learner, args.rounds)
        subprocess.run(
            ["git", "worktree", "add", "--detach", "--quiet", str(before), commit],
            cwd=ROOT,
            check=True,
        )
        try:
            times: dict[str, dict[str, list[float]]] = {"before": {}, "after": {}}
            for _ in range(args.cycles):
                for label, tree in (("before", before), ("after", ROOT)):
                    for key, seconds in time_version(tree, states, args.repeats).items():
                        times[label].setdefault(key, []).extend(seconds)
        finally:
            subprocess.run(
                ["git", "worktree", "remove", "--force", str(before)], cwd=ROOT, check=False
            )
    print(
        f"{args.learner} update after {args.rounds} rounds, {commit[:7]} (before) against "
        f"this checkout (after), {args.cycles} x {args.repeats} updates each\n"
    )
    header = (
        f"{'environment':13s} {'before min':>10s} {'after min':>10s} "
        f"{'before med':>10s} {'after med':>10s} {'after/before':>12s}"
    )
    print(header)
    print("-" * len(header))
    for key in sorted(times["after"], key=lambda k: args.environments.index(k.split("--")[0])):
        old, new = times["before"][key], times["after"][key]
        print(
            f"{key.split('--')[0]:13s} {min(old) * 1e3:8.0f}ms {min(new) * 1e3:8.0f}ms "
            f"{statistics.median(old) * 1e3:8.0f}ms {statistics.median(new) * 1e3:8.0f}ms "
            f"{min(new) / min(old):12.2f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
