"""Behavioural cloning's update runs its momentum steps in one compiled call (``_ascend``,
``compiled_steps = true``, the default). It must do what the steps written with NumPy do
(``compiled_steps = false``: the teacher data's log-likelihood, the table's prior,
``MomentumAscent.step``, the clip), on demonstrations, agent steps with feedback and idle moves,
with every optimiser setting cloning has, and refuse a gradient that is not finite. Not to the
last bit: a step's norm is summed in another order than NumPy's, and three updates of 60 steps
compound that to about 1e-10; the agents' choices are the same."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from server import domains
from server.learners import make
from server.learners.cloning import _ascend
from server.learners.likelihoods import GRADIENT_NOT_FINITE
from server.learners.objective import TeacherData
from tests.learners.test_objective import teach


def assert_same_fit(compiled: Any, plain: Any, tolerance: float) -> None:
    """An update of ``compiled`` against one of ``plain`` (the same learner, NumPy's steps)."""
    result, expected = compiled.update(), plain.update()
    assert result.steps == expected.steps == compiled.settings.steps
    assert result.objective == pytest.approx(expected.objective, rel=tolerance)
    np.testing.assert_allclose(compiled.table, plain.table, rtol=0, atol=tolerance)
    np.testing.assert_allclose(
        compiled.optimizer.velocity, plain.optimizer.velocity, rtol=0, atol=tolerance
    )
    for task in range(len(compiled.env.tasks)):
        np.testing.assert_array_equal(compiled.policy(task), plain.policy(task))


@pytest.mark.parametrize("environment", ["farming-tutorial", "doorway", "flip"])
@pytest.mark.parametrize(
    "settings",
    [{}, {"optimizers": "joint", "momentum_clip": "velocity", "q_bound_sds": None}],
    ids=["reference", "joint"],
)
def test_the_compiled_steps_do_what_the_numpy_steps_do(
    environment: str, settings: dict[str, Any]
) -> None:
    """Three updates of 60 steps (the reference settings: an optimiser per task, the step
    clipped, the table to +-3; and one optimiser, the velocity clipped, no bound)."""
    env = domains.make(environment)
    compiled: Any = make("cloning", env, seed=3, steps=60, **settings)
    plain: Any = make("cloning", env, seed=3, steps=60, compiled_steps=False, **settings)
    for round_ in range(3):
        for learner in (compiled, plain):
            teach(learner, seed=round_, all_tasks=round_ != 1)
        assert_same_fit(compiled, plain, 1e-8)
    assert np.abs(compiled.table).max() > 0.05  # the data moved it


@pytest.mark.parametrize("optimizers", ["per-task", "joint"])
def test_the_compiled_steps_clip_as_the_numpy_steps_do(optimizers: str) -> None:
    """Steps and tables clipped on every step (a large rate): the same to the last bits after
    ten steps. (Over many such steps a last bit's difference grows without bound: a clip
    makes the steps depend on which side of it a value falls.)"""
    env = domains.make("doorway")
    settings = {"learning_rate": 5.0, "max_step": 0.5, "q_bound_sds": 0.5, "steps": 10}
    compiled: Any = make("cloning", env, seed=3, optimizers=optimizers, **settings)
    plain: Any = make(
        "cloning", env, seed=3, optimizers=optimizers, compiled_steps=False, **settings
    )
    for learner in (compiled, plain):
        teach(learner, seed=0)
    assert_same_fit(compiled, plain, 1e-12)
    assert np.abs(compiled.table).max() == 0.5


def test_an_update_with_no_steps_changes_nothing() -> None:
    env = domains.make("doorway")
    learner: Any = make("cloning", env, seed=0, steps=0)
    teach(learner, seed=0)
    result = learner.update()
    assert (result.objective, result.steps) == (0.0, 0)
    assert not learner.table.any()


def test_compiled_steps_is_true_or_false() -> None:
    with pytest.raises(ValueError, match="compiled_steps must be true or false"):
        make("cloning", domains.make("doorway"), compiled_steps="yes")


def test_a_gradient_that_is_not_finite_is_refused() -> None:
    """A zero prior variance divides by zero: the kernel stops with its code, the table as it
    was, and the learner raises rather than store it."""
    env = domains.make("doorway")
    learner: Any = make("cloning", env, seed=0)
    teach(learner, seed=0)
    table = np.ones_like(learner.table)
    learner.table = table
    learner.settings = learner.settings.replace(q_prior_sd=1e-200)  # squared: 0
    *_, code = _ascend(*learner.ascent_arguments(TeacherData.from_log(learner.data), 5))
    assert code == GRADIENT_NOT_FINITE
    assert (table == 1.0).all()
    with pytest.raises(FloatingPointError, match="gradient is not finite"):
        learner.update()
    assert (learner.table == 1.0).all()
