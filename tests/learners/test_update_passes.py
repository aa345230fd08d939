"""The planner passes an update runs, as benchmarks/learners.py --breakdown counts them: BAM's
reference schedule is 10 alternations of 20 cost steps and 20 dynamics steps, one forward and
one reverse pass each (400 of each); model-based IRL plans only in its 200 cost steps (its
dynamics fit never runs the planner). docs/benchmarks.md gives these counts."""

from __future__ import annotations

import numpy as np
import pytest

from server import domains
from server.learners import make, planning
from server.teacher import Teacher
from tests.script_support import ROOT, load_script

bench = load_script(ROOT / "benchmarks" / "learners.py", "learners_benchmark")


@pytest.mark.parametrize(("name", "passes"), [("bam", 400), ("model-based", 200)])
def test_the_breakdown_counts_every_pass_of_an_update(name: str, passes: int) -> None:
    env = domains.make("wall")
    learner = make(name, env, seed=0)
    teacher = Teacher(env, seed=0)
    rng = np.random.default_rng(0)
    for task in range(len(env.tasks)):
        for step in teacher.demonstration(task, env.sample_start(task, rng)):
            learner.record_demonstration(task, *step)
    real = planning.run_pass
    forward, reverse, in_passes, whole = bench.pass_breakdown(env, learner, repeats=1)
    assert (forward, reverse) == (passes, passes)
    assert 0.0 < in_passes < whole
    assert planning.run_pass is real  # the counting wrapper is gone


def test_a_forward_pass_is_counted_in_backups_of_every_state_action_and_task() -> None:
    env = domains.make("flip")
    # The figure: 400 states x 5 actions x 80 backups x 2 tasks, the last backup's
    # value not taken.
    assert bench.backups(env) == 400 * 5 * 79 * 2
