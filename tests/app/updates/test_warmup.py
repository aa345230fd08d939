"""The learners' kernels are loaded (or compiled) by ``warm_up`` before a participant's update
needs them."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

# In a fresh interpreter (this one has compiled the kernels in other tests): warm up, then run
# what an update process runs for a study, and report which kernels gained a compiled
# signature on the way (each would have been compiled, about 7 s, or loaded from the cache on a
# participant's update).
SCRIPT = r"""
import json, numba
import numpy as np
from server import domains, learners
from server.learners import _kernels, likelihoods, planning
from server.app.updates.warmup import warm_up
from server.app.updates.worker import run_update
from server.learners.records import AgentStep, DemonstrationStep, Feedback
from server.teacher import Teacher

def signatures():
    found = {}
    for module in (_kernels, likelihoods, planning):
        for name in dir(module):
            value = getattr(module, name)
            if isinstance(value, numba.core.dispatcher.Dispatcher):
                found[f"{module.__name__}.{name}"] = len(value.signatures)
    return found

warm_up()
warmed = signatures()
rng = np.random.default_rng(1)
for env_name in ("doorway", "flip", "two-fields", "three-fields"):
    env = domains.make(env_name)
    teacher = Teacher(env, seed=2)
    records = []
    for task in range(len(env.tasks)):
        for step in teacher.demonstration(task, env.sample_start(task, rng)):
            records.append(DemonstrationStep(task, *step))
        state = env.sample_start(task, rng)
        for action in (1, 2, 3, 4, 0):
            next_state = env.step(state, action, rng)
            records.append(AgentStep(task, state, action, next_state))
            records.append(Feedback(int(rng.choice([-1, 1]))))
            state = next_state
    for learner in learners.NAMES:
        for threads in (1, 2):
            job = {"environment": env_name, "learner": learner, "seed": 0, "settings": {},
                   "base_state": None, "threads": threads}
            run_update({**job, "records": [], "fit": False})
            first = run_update({**job, "records": records[:8], "fit": True})
            run_update({**job, "records": records[8:], "fit": True,
                        "base_state": first["learner_state"]})
# And the updates a server times at start for its capacity (the paper's study file): longer
# fits, where a step may leave the passes' layouts and take the single dynamics step's path.
from server.app.study_file import load_study_config
from server.app.updates.capacity import measure_updates, reference_jobs
study = load_study_config()
study.register_environments()
measure_updates({"jobs": reference_jobs(study.pairs(), study.settings_of), "warm": False})
after = signatures()
print(json.dumps({"warmed": warmed, "after": after}))
"""


@pytest.mark.slow
def test_warm_up_loads_every_kernel_a_study_s_updates_use() -> None:
    result = subprocess.run(
        [sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=900, check=False
    )
    assert result.returncode == 0, result.stderr[-3000:]
    report = json.loads(result.stdout.strip().splitlines()[-1])
    warmed, after = report["warmed"], report["after"]
    loaded = {name.rsplit(".", 1)[1] for name, count in warmed.items() if count}
    # the passes, on one thread and split, the likelihoods and the evaluation's planner
    assert {
        "soft_forward_tasks",
        "soft_forward_chunks",
        "soft_backward_tasks",
        "soft_backward_chunks",
        "data_log_likelihood_kernel",
        "hard_backups",
    } <= loaded
    gained = {name: (warmed[name], count) for name, count in after.items() if count != warmed[name]}
    assert gained == {}, f"compiled after warm-up (on a participant's update): {gained}"
