"""BAM's and model-based IRL's cost steps in one compiled call (``compiled_steps``, the
default) against the NumPy steps: the same arithmetic but for the norm that clips a step and a
feedback step's sigmoid, so the same costs, velocities and objective to rounding after a few
steps (the steps' clipped momentum then carries rounding apart within a hundred steps, as any
change of an update's last bits does: docs/defaults.md, "Compiled cost steps"); the same
bits on any split of the tasks over threads; errors refused as the NumPy steps refuse them."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from server import domains
from server.learners import make, planning, restore
from server.learners.planner_learner import PlannerLearner
from server.teacher import Teacher
from tests.learners._support import agent_episode, demonstrate_round

STEPS = 3


def taught(
    name: str, learner_name: str, feedback: bool, skip_last_task: bool = False, **settings: Any
) -> PlannerLearner:
    """A learner after three rounds of demonstrations (of every task, or all but the last),
    with random agent episodes and the teacher's feedback if asked, updated after each round by
    the NumPy steps."""
    env = domains.make(name)
    learner = make(learner_name, env, seed=0, compiled_steps=False, **settings)
    assert isinstance(learner, PlannerLearner)
    teacher = Teacher(env, seed=0)
    rng = np.random.default_rng(5)
    for _ in range(3):
        if skip_last_task:
            for task in range(len(env.tasks) - 1):
                for step in teacher.demonstration(task, env.sample_start(task, rng)):
                    learner.record_demonstration(task, *step)
        else:
            demonstrate_round(learner, env, teacher, rng)
        if feedback:
            agent_episode(learner, env, teacher, rng, task=0, steps=15)
        learner.update()
    return learner


def steps_both_ways(learner: PlannerLearner) -> tuple[PlannerLearner, float, PlannerLearner, float]:
    """``STEPS`` cost steps from the learner's state by NumPy and compiled, on its data."""
    state = learner.state_dict()
    numpy_steps = restore(learner.env, state)
    compiled = restore(learner.env, state)
    assert isinstance(numpy_steps, PlannerLearner) and isinstance(compiled, PlannerLearner)
    compiled.settings = compiled.settings.replace(compiled_steps=True)
    data = numpy_steps.teacher_data()
    value = numpy_steps.cost_fit.steps(numpy_steps.operator(data), data, STEPS)
    compiled_value = compiled.cost_fit.steps(compiled.operator(data), data, STEPS)
    return numpy_steps, value, compiled, compiled_value


CASES = [
    # (environment, learner, planner precision, agent steps with feedback)
    ("wall", "bam", "float32", True),
    ("two-rooms", "model-based", "float64", True),
    ("flip", "model-based", "float32", True),  # four states a cell
    ("choices", "bam", "float64", False),
    ("three-fields", "bam", "float64", False),  # planned over the states its data reaches
    ("two-fields", "model-based", "float32", True),  # costs on the fields only
]


@pytest.mark.parametrize(("name", "learner_name", "precision", "feedback"), CASES)
def test_compiled_cost_steps_take_the_numpy_steps(
    name: str, learner_name: str, precision: str, feedback: bool
) -> None:
    learner = taught(name, learner_name, feedback, planner_precision=precision)
    data = learner.teacher_data()
    assert (data.step_tasks.shape[0] > 0) == feedback
    if name == "three-fields":
        assert data.plan_states is not None
    start = learner.costs.copy()
    numpy_steps, value, compiled, compiled_value = steps_both_ways(learner)
    assert np.max(np.abs(numpy_steps.costs - start)) > 1e-3  # the steps moved the costs
    np.testing.assert_allclose(compiled.costs, numpy_steps.costs, rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        compiled.cost_fit.optimizer.velocity,
        numpy_steps.cost_fit.optimizer.velocity,
        rtol=0,
        atol=1e-12,
    )
    assert compiled_value == pytest.approx(value, rel=1e-12)
    # Cells without a cost stay at 0 (farming's dirt).
    assert np.all(compiled.costs[:, ~compiled.cost_fit.mask] == 0.0)


@pytest.mark.parametrize("precision", ["float64", "float32"])
@pytest.mark.parametrize("learner_name", ["bam", "model-based"])
def test_a_task_without_data_takes_its_prior_s_steps(learner_name: str, precision: str) -> None:
    """Doorway's last task untaught: its costs move by the prior's pull alone, as in the NumPy
    steps, beside the taught tasks'."""
    learner = taught(
        "doorway", learner_name, feedback=False, skip_last_task=True, planner_precision=precision
    )
    assert learner.teacher_data().tasks.tolist() == [0, 1, 2]
    learner.costs[3] = np.linspace(-1.0, 1.0, learner.costs.shape[1])  # a prior to pull
    numpy_steps, value, compiled, compiled_value = steps_both_ways(learner)
    assert np.max(np.abs(numpy_steps.costs[3] - learner.costs[3])) > 1e-4
    np.testing.assert_allclose(compiled.costs, numpy_steps.costs, rtol=0, atol=1e-12)
    assert compiled_value == pytest.approx(value, rel=1e-12)


@pytest.mark.parametrize("backend", ["openmp", "python"])
def test_compiled_cost_steps_split_over_threads_give_the_same_bits(
    backend: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each task's steps are its own (its optimiser, its passes): the tasks split over two or
    three threads, on OpenMP's or Python's, give the one-thread update's numbers bit for bit."""
    if backend == "openmp" and not planning.compiled_threads():
        pytest.skip("no OpenMP runtime on this machine")
    if backend == "python":
        monkeypatch.setattr(planning, "_openmp", False)
    learner = taught("two-rooms", "bam", feedback=True)
    state = learner.state_dict()
    results = {}
    for threads in (1, 2, 3):
        with planning.using_planner_threads(threads):
            copy = restore(learner.env, state)
            copy.settings = copy.settings.replace(compiled_steps=True)
            objective = copy.update().objective
        assert isinstance(copy, PlannerLearner)
        results[threads] = (copy.costs, copy.cost_fit.optimizer.velocity, copy.theta, objective)
    for threads in (2, 3):
        for one, split in zip(results[1], results[threads], strict=True):
            np.testing.assert_array_equal(split, one)


def test_a_gradient_that_is_not_finite_is_refused_and_the_costs_stay() -> None:
    """A prior so narrow that its gradient overflows: both ways refuse the step with the same
    error, and the compiled steps leave the learner's costs and velocity as they were."""
    learner = taught("wall", "model-based", feedback=False)
    learner.settings = learner.settings.replace(
        cost_prior_sd=1e-200
    )  # its variance underflows to 0
    state = learner.state_dict()
    for compiled in (False, True):
        copy = restore(learner.env, state)
        assert isinstance(copy, PlannerLearner)
        copy.settings = copy.settings.replace(compiled_steps=compiled)
        costs, velocity = copy.costs.copy(), copy.cost_fit.optimizer.velocity.copy()
        data = copy.teacher_data()
        with pytest.raises(FloatingPointError, match="gradient is not finite"):
            copy.cost_fit.steps(copy.operator(data), data, STEPS)
        if compiled:
            np.testing.assert_array_equal(copy.costs, costs)
            np.testing.assert_array_equal(copy.cost_fit.optimizer.velocity, velocity)


@pytest.mark.parametrize("sd", [0.0, -1.0, float("nan")])
def test_a_prior_deviation_that_is_not_positive_is_refused_both_ways(sd: float) -> None:
    learner = taught("wall", "bam", feedback=False)
    state = learner.state_dict()
    for compiled in (False, True):
        copy = restore(learner.env, state)
        assert isinstance(copy, PlannerLearner)
        copy.settings = copy.settings.replace(compiled_steps=compiled, cost_prior_sd=sd)
        costs = copy.costs.copy()
        data = copy.teacher_data()
        with pytest.raises(ValueError, match="prior standard deviation must be positive"):
            copy.cost_fit.steps(copy.operator(data), data, STEPS)
        np.testing.assert_array_equal(copy.costs, costs)


def test_the_global_cost_learner_has_no_compiled_cost_steps() -> None:
    """Its global cost ties the tasks' steps together: it steps in NumPy, and says so."""
    env = domains.make("wall")
    with pytest.raises(ValueError, match="compiled_steps"):
        make("global-cost", env, compiled_steps=True)
    assert make("bam", env).settings.compiled_steps is True
    assert make("model-based", env).settings.compiled_steps is True


def test_a_state_saved_before_compiled_cost_steps_keeps_the_numpy_steps() -> None:
    """An agent in a study that runs across the upgrade keeps its arithmetic."""
    learner = taught("wall", "bam", feedback=False)
    state = learner.state_dict()
    del state["settings"]["compiled_steps"]
    restored = restore(learner.env, state)
    assert restored.settings.compiled_steps is False
