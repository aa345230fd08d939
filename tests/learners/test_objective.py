"""Every learner's objective gradient equals central finite differences with respect to every
parameter block, on real environments with demonstrations, agent steps with feedback and
idle transitions recorded."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from server import domains, learners
from server.learners.base import Learner
from server.learners.likelihoods import gaussian_log_prior
from server.learners.objective import (
    RESTRICT_BELOW,
    TeacherData,
    action_model,
    feedback_model,
    teacher_log_likelihood,
)
from server.teacher import Teacher
from tests.learners._support import (
    agent_episode,
    central_difference,
    demonstrate_round,
    idle_transitions,
    probe_indices,
)

PLANNER_LEARNERS = [name for name in learners.NAMES if name != "cloning"]
# The parameter blocks each learner's objective must give gradients for.
BLOCKS = {
    "bam": ("theta", "costs"),
    "model-based": ("theta", "costs"),
    "global-cost": ("theta", "costs", "global_costs"),
    "cloning": ("table",),
}


def test_every_learner_has_its_blocks_listed() -> None:
    assert set(learners.NAMES) == set(BLOCKS)


def teach(learner: Learner, seed: int, all_tasks: bool = True) -> None:
    """Demonstrations (of every task, or of the last task only), agent steps with feedback
    for the first task (one given after the step, the study's +/- keys) and idle moves."""
    env = learner.env
    teacher = Teacher(env, seed=seed)
    rng = np.random.default_rng(seed)
    if all_tasks:
        demonstrate_round(learner, env, teacher, rng)
    else:
        last = len(env.tasks) - 1
        for state, action, next_state in teacher.demonstration(last, env.sample_start(last, rng)):
            learner.record_demonstration(last, state, action, next_state)
    agent_episode(learner, env, teacher, rng, task=0, steps=12)
    state = env.sample_start(0, rng)
    learner.record_agent_step(0, state, 1, env.step(state, 1, rng))
    learner.record_feedback(-1)
    idle_transitions(learner, env, rng, count=10)


def randomise(learner: Learner, seed: int) -> None:
    """Parameters away from the initialisation, so that every term of the objective (and the
    teacher data's dependence on the dynamics) is active."""
    rng = np.random.default_rng(seed)
    if hasattr(learner, "theta"):
        learner.theta = learner.theta + rng.normal(0.0, 1.0, learner.theta.shape)
        learner.costs = rng.normal(0.0, 0.5, learner.costs.shape)
    if hasattr(learner, "global_costs"):
        learner.global_costs = rng.normal(0.0, 0.3, learner.global_costs.shape)
    if hasattr(learner, "table"):
        learner.table = rng.normal(0.0, 1.0, learner.table.shape)


def cloning_objective(learner: Any) -> tuple[float, dict[str, np.ndarray]]:
    """Behavioural cloning's objective: ln p(D_T | table) + ln prior(table)."""
    if hasattr(learner, "objective"):
        return learner.objective()
    data = TeacherData.from_log(learner.data)
    value, d_q = teacher_log_likelihood(
        learner.table[data.tasks],
        data,
        action_model(learner.settings),
        feedback_model(learner.settings),
    )
    prior, gradient = gaussian_log_prior(learner.table, 0.0, learner.settings.q_prior_sd)
    gradient = gradient.copy()
    gradient[data.tasks] += d_q
    return value + prior, {"table": gradient}


def objective_of(learner: Any) -> tuple[float, dict[str, np.ndarray]]:
    return cloning_objective(learner) if learner.name == "cloning" else learner.objective()


# The gradient check's tolerance (rtol, atol) by the passes' precision: float32 passes carry
# about 1e-5 relative error into the objective's gradient.
TOLERANCES = {"float64": (1e-5, 1e-6), "float32": (2e-3, 1e-4)}


def check_gradients(learner: Any, seed: int) -> None:
    """The objective's gradient at the learner's precision against central differences of
    its float64 objective (float32's rounding would swamp a difference quotient)."""
    precision = getattr(learner.settings, "planner_precision", "float64")
    rtol, atol = TOLERANCES[precision]
    value, gradients = objective_of(learner)
    assert np.isfinite(value)
    assert set(gradients) == set(BLOCKS[learner.name])
    rng = np.random.default_rng(seed)
    for block in BLOCKS[learner.name]:
        parameters = getattr(learner, block).copy()
        analytic = gradients[block]
        assert analytic.shape == parameters.shape
        assert np.all(np.isfinite(analytic))
        assert np.abs(analytic).max() > 1e-3, block  # not vacuous

        def value_at(x: np.ndarray, block: str = block, shape=parameters.shape) -> float:
            setattr(learner, block, x.reshape(shape))
            if hasattr(learner.settings, "planner_precision"):
                learner.settings = learner.settings.replace(planner_precision="float64")
            try:
                return objective_of(learner)[0]
            finally:
                if hasattr(learner.settings, "planner_precision"):
                    learner.settings = learner.settings.replace(planner_precision=precision)

        indices = probe_indices(analytic, rng, count=6)
        if block == "costs":  # only the cells that carry a cost are parameters (farming)
            fitted = np.broadcast_to(learner.cost_fit.mask, parameters.shape).ravel()
            indices = indices[fitted[indices]]
        numeric = central_difference(value_at, parameters, indices)
        setattr(learner, block, parameters)
        np.testing.assert_allclose(
            analytic.ravel()[indices], numeric, rtol=rtol, atol=atol, err_msg=block
        )


def made(name: str, environment: str, precision: str) -> Any:
    """A learner of ``name`` whose passes run in ``precision`` (cloning has none)."""
    learner = learners.make(name, domains.make(environment), seed=0)
    if hasattr(learner.settings, "planner_precision"):
        learner.settings = learner.settings.replace(planner_precision=precision)
    return learner


@pytest.mark.parametrize("precision", ["float64", "float32"])
@pytest.mark.parametrize("name", learners.NAMES)
@pytest.mark.parametrize("all_tasks", [True, False])
def test_objective_gradients_on_wall(name: str, all_tasks: bool, precision: str) -> None:
    learner = made(name, "wall", precision)
    teach(learner, seed=1, all_tasks=all_tasks)
    randomise(learner, seed=2)
    check_gradients(learner, seed=3)


@pytest.mark.parametrize("precision", ["float64", "float32"])
@pytest.mark.parametrize("name", learners.NAMES)
@pytest.mark.parametrize("environment", ["two-fields", "flip"])
def test_objective_gradients_on_farming_and_gravity(
    name: str, environment: str, precision: str
) -> None:
    learner = made(name, environment, precision)
    teach(learner, seed=4)
    randomise(learner, seed=5)
    check_gradients(learner, seed=6)


@pytest.mark.parametrize("name", PLANNER_LEARNERS)
def test_objective_without_teacher_data_is_dynamics_and_priors(name: str) -> None:
    """Only idle transitions: the costs' gradient is the prior's alone."""
    env = domains.make("wall")
    learner: Any = learners.make(name, env, seed=0)
    idle_transitions(learner, env, np.random.default_rng(7), count=15)
    randomise(learner, seed=8)
    _, gradients = learner.objective()
    np.testing.assert_allclose(
        gradients["costs"], -learner.costs / learner.settings.cost_prior_sd**2, rtol=1e-12
    )
    check_gradients(learner, seed=9)


def test_bam_update_increases_equation_5() -> None:
    env = domains.make("wall")
    learner: Any = learners.make("bam", env, seed=0)
    teach(learner, seed=10)
    before, _ = learner.objective()
    learner.update()
    after, _ = learner.objective()
    assert after > before + 1.0


def test_cloning_update_increases_its_objective() -> None:
    env = domains.make("wall")
    learner: Any = learners.make("cloning", env, seed=0)
    teach(learner, seed=11)
    before, _ = cloning_objective(learner)
    learner.update()
    after, _ = cloning_objective(learner)
    assert after > before + 1.0


@pytest.mark.parametrize("precision", ["float64", "float32"])
@pytest.mark.parametrize("name", PLANNER_LEARNERS)
def test_planning_over_the_states_the_data_reaches_changes_no_bit(
    name: str, precision: str
) -> None:
    """Three-fields' data reaches part of its states (machines that cannot be carried into a
    field): updates plan over those only. The teacher-data likelihood, its gradient on every
    task's rewards (0 out of reach) and its pull-back to theta equal the whole model's to the
    last bit in float64 passes, with demonstrations, agent steps and feedback. Float32 passes'
    reverse passes sum a next state's terms in the order of the forward pass's layout, which
    depends on the states planned: there they agree to float32's rounding."""
    env = domains.make("three-fields")
    learner: Any = learners.make(name, env, seed=3, planner_precision=precision)
    teach(learner, seed=3)
    randomise(learner, seed=3)
    whole = TeacherData.from_log(learner.data)
    part = whole.restricted(env.model)
    assert part.plan_states is not None and part.plan_model is not None
    assert 0 < len(part.plan_states) < env.num_states
    assert part.restricted(env.model) is part
    np.testing.assert_array_equal(
        part.visited(len(env.tasks), env.num_states), whole.visited(len(env.tasks), env.num_states)
    )
    results = []
    for data in (whole, part):
        value, d_rewards, d_transitions = learner.cost_fit.teacher_objective(
            learner.operator(data), data, need_transitions=True
        )
        results.append((value, d_rewards, learner.pullback(data, d_transitions)))
    (value, d_rewards, d_theta), (part_value, part_d_rewards, part_d_theta) = results
    assert part_value == value
    assert d_rewards.shape == part_d_rewards.shape == (len(whole.tasks), env.num_states)
    if precision == "float64":
        np.testing.assert_array_equal(part_d_rewards.view(np.uint64), d_rewards.view(np.uint64))
        np.testing.assert_array_equal(part_d_theta.view(np.uint64), d_theta.view(np.uint64))
    else:
        scale = np.abs(d_rewards).max()
        np.testing.assert_allclose(part_d_rewards, d_rewards, rtol=1e-4, atol=1e-5 * scale)
        np.testing.assert_allclose(
            part_d_theta, d_theta, rtol=1e-4, atol=1e-5 * np.abs(d_theta).max()
        )
    assert np.abs(d_theta).max() > 1e-3 and np.abs(d_rewards[:, part.plan_states]).max() > 1e-3


def test_data_that_reaches_every_state_plans_over_all_of_them() -> None:
    env = domains.make("doorway")
    learner: Any = learners.make("bam", env, seed=3)
    teach(learner, seed=3)
    data = TeacherData.from_log(learner.data)
    assert data.restricted(env.model) is data
    empty = TeacherData.from_log(learners.make("bam", env).data)
    assert empty.restricted(env.model) is empty


def test_data_that_reaches_nearly_every_state_plans_over_all_of_them() -> None:
    """Two-fields' data reaches all but a few of its states: renumbering the rest would break
    the grid's offsets that the passes' shifted rows use, so it plans over every state."""
    env = domains.make("two-fields")
    learner: Any = learners.make("bam", env, seed=3)
    teach(learner, seed=3)
    data = TeacherData.from_log(learner.data)
    reached = env.model.reachable(np.concatenate([data.demo_states, data.step_states]))
    assert RESTRICT_BELOW * env.num_states < len(reached) < env.num_states
    assert data.restricted(env.model) is data


@pytest.mark.parametrize("optimizer", ["momentum", "lbfgs"])
@pytest.mark.parametrize("name", PLANNER_LEARNERS)
def test_an_update_from_costs_that_are_not_finite_stops_with_an_error(
    name: str, optimizer: str
) -> None:
    # A learner's steps plan on its costs without checking them again (they are checked where
    # they are made): a NaN that got in anyway still stops the update.
    env = domains.make("wall")
    learner = learners.make(name, env, seed=0, optimizer=optimizer)
    teach(learner, seed=0)
    learner.costs[0, int(np.flatnonzero(env.cost_cells)[0])] = np.nan
    with pytest.raises(FloatingPointError, match="not finite"):
        learner.update()
