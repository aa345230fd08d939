"""The planner learners' two collaborators (``server.learners.fits``): a cost fit and a
dynamics fit each work on their own, without a learner, and a planner learner's steps are
theirs."""

from __future__ import annotations

import numpy as np
import pytest

from server import domains, learners
from server.learners.bam import BAM, BAMSettings
from server.learners.cost_fit import CellCosts
from server.learners.dynamics_fit import ThetaFit
from server.learners.global_cost import GlobalCellCosts, GlobalCostIRL, GlobalCostSettings
from server.learners.planner_learner import PlannerLearner
from server.learners.planning import TransitionOperator
from server.teacher import Teacher

STEPS = 5


def taught(name: str) -> PlannerLearner:
    env = domains.make("wall")
    learner = learners.make(name, env, seed=0)
    assert isinstance(learner, PlannerLearner)
    teacher, rng = Teacher(env, seed=0), np.random.default_rng(0)
    for task in range(len(env.tasks)):
        for state, action, next_state in teacher.demonstration(task, env.sample_start(task, rng)):
            learner.record_demonstration(task, state, action, next_state)
    return learner


@pytest.mark.parametrize("name", ["bam", "global-cost"])
def test_a_cost_fit_alone_takes_the_learners_cost_steps(name: str) -> None:
    """Costs fitted on a fixed table by a cost fit made on its own, with the learner's
    settings, end where the learner's own cost fit ends."""
    learner = taught(name)
    env, data = learner.env, learner.teacher_data()
    fit_type = GlobalCellCosts if isinstance(learner, GlobalCostIRL) else CellCosts
    alone = fit_type(env, learner.settings)
    table = TransitionOperator.of_model(learner.plan_model(data), learner.theta)
    value = alone.steps(table, data, STEPS)
    assert value == learner.cost_fit.steps(learner.operator(data), data, STEPS)
    np.testing.assert_array_equal(alone.costs, learner.costs)
    np.testing.assert_array_equal(alone.optimizer.velocity, learner.cost_fit.optimizer.velocity)
    assert np.any(alone.costs != 0.0)


def test_a_dynamics_fit_alone_takes_the_learners_dynamics_steps() -> None:
    learner = taught("model-based")
    env = learner.env
    observed = env.model.observe(learner.data.observed_transitions())
    alone = ThetaFit(env, learner.settings)
    assert alone.steps(observed, STEPS) == learner.dynamics_fit.steps(observed, STEPS)
    np.testing.assert_array_equal(alone.theta, learner.theta)
    assert np.any(alone.theta != env.model.initial_parameters())


def test_the_learner_hands_new_settings_to_its_fits() -> None:
    learner = taught("bam")
    changed = learner.settings.replace(planner_precision="float64", compiled_steps=False)
    learner.settings = changed
    assert learner.dynamics_fit.settings is changed and learner.cost_fit.settings is changed
    assert not learner.cost_fit.compiled
    with pytest.raises(TypeError, match="PlannerSettings"):
        learner.settings = learners.learner_class("cloning").settings_type()


def test_the_saved_state_holds_both_fits_parameters() -> None:
    learner = taught("global-cost")
    learner.update()
    state = learner.state_dict()
    assert set(state["parameters"]) == {
        "theta", "theta_velocity", "costs", "cost_velocity", "global_costs", "global_velocity",
        "fitted_tasks",
    }  # fmt: skip
    restored = learners.restore(learner.env, state)
    assert isinstance(restored, GlobalCostIRL)
    np.testing.assert_array_equal(restored.global_costs, learner.global_costs)
    np.testing.assert_array_equal(restored.theta, learner.theta)
    assert isinstance(learner.settings, GlobalCostSettings)
    assert isinstance(BAM(learner.env).settings, BAMSettings)
