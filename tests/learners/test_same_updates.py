"""The planner learners' updates at their defaults learn what they learned before: two updates
of BAM and of model-based IRL, in every environment, from two rounds of the simulated
teacher's demonstrations, end at the parameters (theta and the costs) and optimiser velocities
recorded in ``update_reference.npz`` at commit 7463029. A change that makes updates cheaper
(docs/benchmarks.md, "Where an update's time goes") must keep them, or be a named setting.

Tolerance: 1e-12 relative plus 1e-12 absolute. On the AVX-512 AMD EPYC the updates meet the
reference to the last bit (the compiled passes do the same operations in the same order); a
change of the arithmetic an update depends on compounds over its 400 steps far beyond it.

Record again only for a change meant to alter what agents learn (then rerun the demonstrations
experiment, docs/reproduction.md): ``python -m tests.learners.test_same_updates --record``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from server import domains
from server.learners import make
from server.teacher import Teacher

REFERENCE = Path(__file__).with_name("update_reference.npz")
LEARNERS = ("bam", "model-based")
ROUNDS = 2
FIELDS = ("theta", "costs", "theta_velocity", "cost_velocity")
TOLERANCE = 1e-12
SLOW = {"flip", "choices", "two-fields", "three-fields"}


def updated_parameters(env_name: str, learner_name: str) -> dict[str, np.ndarray]:
    """A learner's parameters after ``ROUNDS`` rounds of demonstrations, updated after each."""
    env = domains.make(env_name)
    learner = make(learner_name, env, seed=0)
    teacher = Teacher(env, seed=0)
    rng = np.random.default_rng(0)
    for _ in range(ROUNDS):
        for task in range(len(env.tasks)):
            for step in teacher.demonstration(task, env.sample_start(task, rng)):
                learner.record_demonstration(task, *step)
        learner.update()
    state = learner._parameters_state()  # type: ignore[attr-defined]
    return {field: np.asarray(state[field], dtype=np.float64) for field in FIELDS}


def cases() -> list[object]:
    return [
        pytest.param(env, name, marks=[pytest.mark.slow] if env in SLOW else [])
        for env in domains.ENVIRONMENTS
        for name in LEARNERS
    ]


@pytest.mark.parametrize(("env_name", "learner_name"), cases())
def test_an_update_learns_what_it_learned_before(env_name: str, learner_name: str) -> None:
    with np.load(REFERENCE) as reference:
        expected = {field: reference[f"{env_name}/{learner_name}/{field}"] for field in FIELDS}
    got = updated_parameters(env_name, learner_name)
    for field in FIELDS:
        assert got[field].shape == expected[field].shape, field
        np.testing.assert_allclose(
            got[field], expected[field], rtol=TOLERANCE, atol=TOLERANCE, err_msg=field
        )


def test_the_reference_moved_the_parameters() -> None:
    """The recorded updates did learn (a reference of untouched parameters would pass any
    learner that does nothing)."""
    with np.load(REFERENCE) as reference:
        for env_name in domains.ENVIRONMENTS:
            env = domains.make(env_name)
            for name in LEARNERS:
                costs = reference[f"{env_name}/{name}/costs"]
                theta = reference[f"{env_name}/{name}/theta"]
                assert np.abs(costs).max() > 1e-3
                assert np.abs(theta - env.model.initial_parameters()).max() > 1e-3


def record() -> None:
    arrays = {}
    for env_name in domains.ENVIRONMENTS:
        for name in LEARNERS:
            for field, values in updated_parameters(env_name, name).items():
                arrays[f"{env_name}/{name}/{field}"] = values
            print(env_name, name, flush=True)
    np.savez_compressed(REFERENCE, **arrays)


if __name__ == "__main__":
    if sys.argv[1:] != ["--record"]:
        sys.exit("usage: python -m tests.learners.test_same_updates --record")
    record()
