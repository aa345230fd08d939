"""BAM's and model-based IRL's momentum steps on the dynamics parameters in compiled calls
(``compiled_dynamics_steps``, the default) against the NumPy steps: the observed transitions'
likelihood, the dynamics prior, the teacher data's gradient pulled back to theta and the clipped
momentum step, element by element in the same order but for the C library's tanh, exp and log
and the norm that clips a step, so the same theta, velocity and objective to rounding after a
few steps, in every model space (sigmoid and softmax primitives, the authors' farming rule, the
gravity prior, a table planned over the states the data reaches); errors refused as the NumPy
steps refuse them, with the learner untouched."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from server import domains
from server.learners import make, planning, restore
from server.learners.bam import BAM
from server.learners.planner_learner import PlannerLearner
from server.teacher import Teacher
from tests.learners._support import agent_episode, demonstrate_round

STEPS = 4


def taught(name: str, learner_name: str, **settings: Any) -> PlannerLearner:
    """A learner after three rounds of demonstrations and an agent episode with the teacher's
    feedback, updated after each round by the NumPy steps."""
    env = domains.make(name)
    learner = make(learner_name, env, seed=0, compiled_dynamics_steps=False, **settings)
    assert isinstance(learner, PlannerLearner)
    teacher = Teacher(env, seed=0)
    rng = np.random.default_rng(7)
    for _ in range(3):
        demonstrate_round(learner, env, teacher, rng)
        agent_episode(learner, env, teacher, rng, task=0, steps=15)
        learner.update()
    return learner


def both_ways(learner: PlannerLearner, compiled: bool) -> PlannerLearner:
    copy = restore(learner.env, learner.state_dict())
    assert isinstance(copy, PlannerLearner)
    copy.settings = copy.settings.replace(compiled_dynamics_steps=compiled)
    return copy


def observed_of(learner: PlannerLearner) -> Any:
    return learner.env.model.observe(learner.data.observed_transitions())


CASES = [
    # (environment, learner, settings): the model space and rule each exercises
    ("wall", "bam", {}),  # sigmoid primitives, the exact gradient
    ("flip", "bam", {}),  # softmax rows with the gravity prior N(0, 1)
    ("choices", "model-based", {"momentum_clip": "velocity"}),  # the clipped step kept
    ("two-fields", "bam", {}),  # the authors' farming rule, observed and taught
    ("two-fields", "model-based", {"dynamics_gradient": "exact"}),
    ("three-fields", "bam", {}),  # the teacher's table over the states its data reaches
    ("three-rooms", "model-based", {"dynamics_prior_sd": 2.0}),  # a prior of the settings
]


@pytest.mark.parametrize(("name", "learner_name", "settings"), CASES)
def test_compiled_dynamics_steps_take_the_numpy_steps(
    name: str, learner_name: str, settings: dict[str, Any]
) -> None:
    learner = taught(name, learner_name, **settings)
    # Away from the optimum the NumPy steps reached (model-based IRL's 200 a round), so that
    # these steps move theta.
    learner.theta = learner.theta + np.random.default_rng(3).normal(0.0, 0.5, learner.theta.shape)
    results = []
    for compiled in (False, True):
        copy = both_ways(learner, compiled)
        assert copy.dynamics_fit.compiled is compiled
        observed = observed_of(copy)
        data = copy.teacher_data()
        if name == "three-fields":
            assert data.plan_states is not None
        values = []
        if isinstance(copy, BAM):
            cost_prior, _ = copy.cost_fit.prior(copy.costs)
            for _ in range(STEPS):
                values.append(copy._dynamics_step(data, observed, cost_prior))
        else:
            values.append(copy.dynamics_fit.steps(observed, STEPS))
        results.append((copy.theta.copy(), copy.dynamics_fit.optimizer.velocity.copy(), values))
    (theta, velocity, values), (compiled_theta, compiled_velocity, compiled_values) = results
    assert np.max(np.abs(theta - learner.theta)) > 1e-3  # the steps moved theta
    np.testing.assert_allclose(compiled_theta, theta, rtol=0, atol=1e-11)
    np.testing.assert_allclose(compiled_velocity, velocity, rtol=0, atol=1e-11)
    np.testing.assert_allclose(compiled_values, values, rtol=1e-12)
    bound = learner.env.model.parameter_bound
    if bound is not None:
        assert np.all(np.abs(compiled_theta) <= bound)


GRADIENT_CASES = [
    # (environment, learner, planner precision): the reverse pass's layouts each exercises
    ("doorway", "bam", "float32"),  # the moved entries summed in runs
    ("flip", "bam", "float64"),  # the table by next state
    ("three-fields", "bam", "float32"),  # planned over the states the data reaches
]


@pytest.mark.parametrize(("name", "learner_name", "precision"), GRADIENT_CASES)
@pytest.mark.parametrize("feedback", [False, True])
def test_the_compiled_teacher_gradient_is_the_passes_one(
    name: str, learner_name: str, precision: str, feedback: bool
) -> None:
    """The same passes and likelihood in one call: the same value and dL/dT to the last bit
    from demonstrations; with the teacher's feedback, to rounding (a feedback step's sigmoid
    takes the C library's tanh)."""
    env = domains.make(name)
    learner = make(learner_name, env, seed=0, planner_precision=precision)
    assert isinstance(learner, PlannerLearner)
    teacher = Teacher(env, seed=0)
    rng = np.random.default_rng(2)
    for _ in range(2):
        demonstrate_round(learner, env, teacher, rng)
        if feedback:
            agent_episode(learner, env, teacher, rng, task=0, steps=15)
        learner.update()
    data = learner.teacher_data()
    value, _, d_transitions = learner.cost_fit.teacher_objective(learner.operator(data), data, True)
    compiled_value, compiled_d = learner.teacher_gradient(data)
    assert compiled_d.shape == d_transitions.shape
    assert np.count_nonzero(compiled_d) > 0
    if feedback:
        assert compiled_value == pytest.approx(value, rel=1e-12)
        np.testing.assert_allclose(compiled_d, d_transitions, rtol=1e-9, atol=1e-12)
    else:
        assert compiled_value == value
        np.testing.assert_array_equal(compiled_d, d_transitions)


def test_the_compiled_teacher_gradient_refuses_what_the_passes_refuse() -> None:
    """A demonstration's state out of the table's range: the likelihood's own error."""
    learner = taught("wall", "bam")
    data = learner.teacher_data()
    broken = dataclasses.replace(data, demo_states=data.demo_states + learner.env.num_states)
    for compiled in (False, True):
        copy = both_ways(learner, compiled)
        with pytest.raises(ValueError, match="index is out of range"):
            copy.teacher_gradient(broken)


LOOP_CASES = [
    ("wall", "float32"),  # the moved entries summed in runs
    ("flip", "float64"),  # the table by next state filled too
    ("two-fields", "float32"),  # the authors' farming rule
    ("three-fields", "float32"),  # planned over the states the data reaches
]


@pytest.mark.parametrize(("name", "precision"), LOOP_CASES)
def test_bam_s_dynamics_steps_in_one_call_take_its_steps_one_by_one(
    name: str, precision: str
) -> None:
    """The table at each theta made and laid out in the kernel: the same theta, velocity and
    objective as the steps that make it in NumPy, to rounding (its primitives' tanh and exp
    are the C library's)."""
    learner = taught(name, "bam", planner_precision=precision)
    learner.theta = learner.theta + np.random.default_rng(4).normal(0.0, 0.5, learner.theta.shape)
    assert isinstance(learner, BAM)
    results = []
    for whole in (False, True):
        copy = both_ways(learner, compiled=True)
        assert isinstance(copy, BAM)
        observed, data = observed_of(copy), copy.teacher_data()
        cost_prior, _ = copy.cost_fit.prior(copy.costs)
        if whole:
            value, done = copy.dynamics_steps_in_one_call(data, observed, STEPS)
            assert done == STEPS
            value += cost_prior
        else:
            for _ in range(STEPS):
                value = copy._dynamics_step(data, observed, cost_prior)
        results.append((copy.theta.copy(), copy.dynamics_fit.optimizer.velocity.copy(), value))
    (theta, velocity, value), (whole_theta, whole_velocity, whole_value) = results
    assert np.max(np.abs(theta - learner.theta)) > 1e-3
    np.testing.assert_allclose(whole_theta, theta, rtol=0, atol=1e-10)
    np.testing.assert_allclose(whole_velocity, velocity, rtol=0, atol=1e-10)
    assert whole_value == pytest.approx(value, rel=1e-10)


def test_a_table_whose_zeros_leave_the_layouts_is_stepped_outside(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Where a step's table has a moved entry at zero that the passes' layouts hold non-zero
    (or the reverse), the kernel stops before it with theta as it was, and an update takes
    those steps the other way and learns what the kernel would have."""
    learner = taught("doorway", "bam")
    assert isinstance(learner, BAM)
    learner.settings = learner.settings.replace(
        warm_share=0.2
    )  # two alternations: rounding has no time to grow
    reference = both_ways(learner, compiled=True)
    reference.update()
    real = planning.TransitionOperator.layout

    def moved_zeros(operator: planning.TransitionOperator) -> Any:
        layout = real.fget(operator)  # type: ignore[attr-defined]
        flipped = layout.nonzero.copy()
        flipped[0] = not flipped[0]  # as if theta had moved the table's zeros
        return dataclasses.replace(layout, nonzero=flipped)

    monkeypatch.setattr(planning.TransitionOperator, "layout", property(moved_zeros))
    theta = learner.theta.copy()
    value, done = learner.dynamics_steps_in_one_call(
        learner.teacher_data(), observed_of(learner), STEPS
    )
    assert done == 0 and np.isnan(value)
    np.testing.assert_array_equal(learner.theta, theta)
    learner.update()
    assert learner.updates == reference.updates
    np.testing.assert_allclose(learner.theta, reference.theta, rtol=0, atol=1e-9)
    np.testing.assert_allclose(learner.costs, reference.costs, rtol=0, atol=1e-9)


def test_a_whole_update_learns_the_same_both_ways() -> None:
    """Doorway's BAM update (its dynamics steps and the walls learned through the teacher's
    data): the same theta and costs to rounding."""
    learner = taught("doorway", "bam")
    learner.settings = learner.settings.replace(
        warm_share=0.2
    )  # two alternations: rounding has no time to grow
    updated = []
    for compiled in (False, True):
        copy = both_ways(learner, compiled)
        copy.update()
        updated.append(copy)
    np.testing.assert_allclose(updated[1].theta, updated[0].theta, rtol=0, atol=1e-9)
    np.testing.assert_allclose(updated[1].costs, updated[0].costs, rtol=0, atol=1e-9)


def test_an_impossible_observed_transition_is_refused_both_ways() -> None:
    """A transition no theta of the model space gives (a jump across the grid): the same error,
    and the compiled steps leave theta and its velocity as they were."""
    learner = taught("wall", "model-based")
    env = learner.env
    far = env.state_of(env.height - 1, env.width - 1)
    observed = env.model.observe(np.array([[env.state_of(0, 0), 0, far]]))
    for compiled in (False, True):
        copy = both_ways(learner, compiled)
        theta, velocity = copy.theta.copy(), copy.dynamics_fit.optimizer.velocity.copy()
        with pytest.raises(ValueError, match=r"observed transition \(0, 0, \d+\) is impossible"):
            copy.dynamics_fit.steps(observed, STEPS)
        np.testing.assert_array_equal(copy.theta, theta)
        np.testing.assert_array_equal(copy.dynamics_fit.optimizer.velocity, velocity)


def test_a_gradient_that_is_not_finite_is_refused_and_theta_stays() -> None:
    learner = taught("flip", "bam")
    for compiled in (False, True):
        copy = both_ways(learner, compiled)
        data = copy.teacher_data()
        _, _, d_transitions = copy.cost_fit.teacher_objective(copy.operator(data), data, True)
        assert d_transitions is not None
        d_transitions = d_transitions.copy()
        d_transitions.reshape(-1)[copy.plan_model(data).flat_parametric_entries[0]] = np.inf
        theta, velocity = copy.theta.copy(), copy.dynamics_fit.optimizer.velocity.copy()
        # (NumPy warns of the inf - inf its softmax pull-back meets on the way.)
        with np.errstate(invalid="ignore"), pytest.raises(FloatingPointError, match="not finite"):
            copy.dynamics_fit.steps(observed_of(copy), 1, copy.plan_model(data), d_transitions)
        if compiled:
            np.testing.assert_array_equal(copy.theta, theta)
            np.testing.assert_array_equal(copy.dynamics_fit.optimizer.velocity, velocity)


@pytest.mark.parametrize("sd", [0.0, -1.0])
def test_a_dynamics_prior_deviation_that_is_not_positive_is_refused_both_ways(sd: float) -> None:
    """Refused where the settings are made; and the steps refuse it themselves, both ways
    (the settings' check passed by, as a state's settings could not be)."""
    learner = taught("wall", "model-based")
    with pytest.raises(ValueError, match="dynamics_prior_sd must be a positive number"):
        learner.settings.replace(dynamics_prior_sd=sd)
    for compiled in (False, True):
        copy = both_ways(learner, compiled)
        object.__setattr__(copy.settings, "dynamics_prior_sd", sd)  # past the frozen check
        theta = copy.theta.copy()
        with pytest.raises(ValueError, match="prior standard deviation must be positive"):
            copy.dynamics_fit.steps(observed_of(copy), STEPS)
        np.testing.assert_array_equal(copy.theta, theta)


def test_the_global_cost_learner_keeps_its_numpy_dynamics_steps() -> None:
    env = domains.make("wall")
    with pytest.raises(ValueError, match="compiled_dynamics_steps"):
        make("global-cost", env, compiled_dynamics_steps=True)
    assert not make("global-cost", env).dynamics_fit.compiled
    assert make("bam", env).dynamics_fit.compiled
    assert make("model-based", env).dynamics_fit.compiled


def test_a_state_saved_before_compiled_dynamics_steps_keeps_the_numpy_steps() -> None:
    """An agent in a study that runs across the upgrade keeps its arithmetic."""
    learner = taught("wall", "bam")
    state = learner.state_dict()
    del state["settings"]["compiled_dynamics_steps"]
    restored = restore(learner.env, state)
    assert restored.settings.compiled_dynamics_steps is False
    assert isinstance(restored, PlannerLearner) and not restored.dynamics_fit.compiled
