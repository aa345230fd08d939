"""Each aspect in which our learners, domains and teacher follow the paper authors' own
implementation (docs/fidelity.md), pinned: the optimiser's clipping, the
model spaces and their priors, the farming cost cells, the authors' farming update, cloning,
the action model's zero-variance rule, the gravity rule and the return's counting."""

from __future__ import annotations

import numpy as np
import pytest

from server import domains
from server.domains.base import DOWN, LEFT, RIGHT, STAY, UP
from server.domains.farming import MACHINES, TERRAINS
from server.domains.gravity import FORBIDDEN, GRAVITIES
from server.learners import make as make_learner
from server.learners.evaluation import optimal_returns
from server.learners.likelihoods import ActionModel, demonstration_log_likelihood
from server.learners.objective import MomentumAscent
from server.teacher import Teacher
from tests.learners._support import central_difference

# -- the optimiser ------------------------------------------------------------------------


def test_clipped_momentum_keeps_the_velocity_and_clips_only_the_applied_step() -> None:
    optimizer = MomentumAscent(3, learning_rate=1.0, momentum=0.7, max_step=0.1)
    gradient = np.array([3.0, 4.0, 0.0])  # norm 5
    after_one = optimizer.step(np.zeros(3), gradient)
    assert np.allclose(optimizer.velocity, gradient)  # not clipped
    assert np.linalg.norm(after_one) == pytest.approx(0.1)
    after_two = optimizer.step(after_one, -0.5 * gradient)
    # velocity 0.7 * g - 0.5 * g = 0.2 g (norm 1): the applied step is clipped to 0.1 along it
    assert np.allclose(optimizer.velocity, 0.2 * gradient)
    assert np.allclose(after_two - after_one, 0.1 * gradient / 5.0)


def test_the_clipped_velocity_rule_stays_a_named_alternative() -> None:
    optimizer = MomentumAscent(3, 1.0, 0.7, 0.1, clip="velocity")
    optimizer.step(np.zeros(3), np.array([3.0, 4.0, 0.0]))
    assert np.linalg.norm(optimizer.velocity) == pytest.approx(0.1)
    with pytest.raises(ValueError, match="momentum_clip"):
        MomentumAscent(3, 1.0, 0.7, 0.1, clip="both")


def test_each_task_s_step_is_clipped_on_its_own() -> None:
    """Per-task optimisers: a task with a large gradient is clipped to 0.1 while a task with a
    small one takes its whole step (a joint clip would shrink it too)."""
    optimizer = MomentumAscent(4, learning_rate=1.0, momentum=0.7, max_step=0.1, rows=2)
    step = optimizer.step(np.zeros(4), np.array([10.0, 0.0, 0.01, 0.02]))
    assert np.allclose(step, [0.1, 0.0, 0.01, 0.02])
    joint = MomentumAscent(4, 1.0, 0.7, 0.1).step(np.zeros(4), np.array([10.0, 0.0, 0.01, 0.02]))
    assert abs(joint[2]) < 0.01


@pytest.mark.parametrize("name", ["bam", "model-based", "global-cost"])
def test_planner_learners_default_to_the_authors_optimiser(name: str) -> None:
    env = domains.make("two-fields")
    learner = make_learner(name, env)
    assert learner.cost_fit.optimizer.clip == "step"
    assert learner.cost_fit.optimizer.rows == len(env.tasks)
    assert learner.dynamics_fit.optimizer.clip == "step"


# -- model spaces and priors ---------------------------------------------------------------


def test_navigation_has_no_prior_on_the_dynamics() -> None:
    learner = make_learner("bam", domains.make("doorway"))
    value, gradient = learner.dynamics_fit.prior(np.full(learner.theta.shape, 5.0))
    assert value == 0.0 and not gradient.any()


def test_gravity_has_the_authors_unit_normal_prior_and_clips_at_50() -> None:
    env = domains.make("flip")
    learner = make_learner("bam", env)
    theta = np.linspace(-2, 2, env.model.num_parameters)
    value, gradient = learner.dynamics_fit.prior(theta)
    assert value == pytest.approx(-0.5 * (theta**2).sum())
    assert np.allclose(gradient, -theta)
    learner.theta = np.full(env.model.num_parameters, 49.99)
    learner.dynamics_fit.step(np.full(env.model.num_parameters, 1e6))
    assert learner.theta.max() == 50.0


def test_farming_is_four_terrains_without_prior_from_a_quarter_and_clips_at_50() -> None:
    env = domains.make("two-fields")
    assert TERRAINS == ("dirt", "soil", "grass", "crops")
    assert env.model.num_parameters == len(MACHINES) * 4
    p = env.model.primitives(env.model.initial_parameters())
    assert np.allclose(p, 0.25)
    learner = make_learner("model-based", env)
    value, gradient = learner.dynamics_fit.prior(np.full(env.model.num_parameters, 7.0))
    assert value == 0.0 and not gradient.any()
    learner.theta = np.full(env.model.num_parameters, -49.99)
    learner.dynamics_fit.step(np.full(env.model.num_parameters, -1e6))
    assert learner.theta.min() == -50.0


def test_a_named_gaussian_prior_replaces_the_model_space_s_own() -> None:
    learner = make_learner("bam", domains.make("doorway"), dynamics_prior_sd=3.0)
    value, _ = learner.dynamics_fit.prior(learner.theta + 3.0)
    assert value == pytest.approx(-0.5 * learner.theta.size)
    with pytest.raises(ValueError, match="dynamics_prior_sd"):
        make_learner("bam", domains.make("doorway"), dynamics_prior_sd=-1.0)


# -- farming: cost cells, the STAY rows, the authors' update --------------------------------


def farming_learner(name: str, **settings):
    env = domains.make("two-fields")
    learner = make_learner(name, env, seed=0, **settings)
    teacher = Teacher(env, seed=0)
    rng = np.random.default_rng(0)
    for task in range(len(env.tasks)):
        for state, action, next_state in teacher.demonstration(task, env.sample_start(task, rng)):
            learner.record_demonstration(task, state, action, next_state)
    learner.update()
    return env, learner


@pytest.mark.parametrize("name", ["bam", "model-based", "global-cost"])
def test_farming_costs_are_zero_on_dirt_for_every_planner_learner(name: str) -> None:
    short = {"cost_steps": 5, "dynamics_steps": 5, **({"alternations": 2} if name == "bam" else {})}
    env, learner = farming_learner(name, **short)
    dirt = ~env.cost_cells
    assert dirt.sum() == env.num_cells - 8  # two 2x2 fields
    assert not learner.costs[:, dirt].any()
    assert learner.costs[:, env.cost_cells].any()
    # "every" puts costs on the dirt too (the named alternative).
    _, every = farming_learner(name, cost_cells="every", **short)
    assert every.costs[:, dirt].any()


def test_stay_on_a_field_carrying_a_machine_is_a_two_entry_row_to_the_same_state() -> None:
    env = domains.make("two-fields")
    state = env.state_of(1, 1, env.feature_names.index("sprinkler"))
    theta = np.random.default_rng(1).normal(size=env.model.num_parameters)
    row = env.model.probabilities(theta)[state, STAY]
    assert list(env.model.next_states[state, STAY]) == [state, state]
    p = env.model.primitives(theta)[MACHINES.index("sprinkler") * 4 + TERRAINS.index("soil")]
    assert row == pytest.approx([p, 1 - p])
    assert list(env.model.outcomes[state, STAY]) == [1, 1]


def ln_p_gradient(env, theta: np.ndarray, k: int) -> np.ndarray:
    """d ln p[k] / d theta, by finite differences."""
    return central_difference(lambda t: float(np.log(env.model.primitives(t)[k])), theta)


def ln_q_gradient(env, theta: np.ndarray, k: int) -> np.ndarray:
    """d ln (1 - p[k]) / d theta, by finite differences."""
    return central_difference(lambda t: float(np.log(1 - env.model.primitives(t)[k])), theta)


def test_the_authors_farming_update_on_observed_transitions() -> None:
    """A success adds 2 d ln p, a failure d ln(1 - p) - d ln p, a STAY on a field d 2 ln p;
    the exact rule gives d ln p, d ln(1 - p) and 0."""
    env = domains.make("two-fields")
    theta = np.random.default_rng(2).normal(size=env.model.num_parameters)
    plow = env.feature_names.index("plow")
    harvester = env.feature_names.index("harvester")
    k_plow_soil = MACHINES.index("plow") * 4 + TERRAINS.index("soil")
    k_harvester_soil = MACHINES.index("harvester") * 4 + TERRAINS.index("soil")
    success = (env.state_of(1, 0, plow), RIGHT, env.state_of(1, 1, plow))
    failure = (env.state_of(1, 0, harvester), RIGHT, env.state_of(1, 0, harvester))
    stay = (env.state_of(1, 1, plow), STAY, env.state_of(1, 1, plow))
    model = env.model
    cases = [
        (
            success,
            2 * ln_p_gradient(env, theta, k_plow_soil),
            ln_p_gradient(env, theta, k_plow_soil),
        ),
        (
            failure,
            ln_q_gradient(env, theta, k_harvester_soil)
            - ln_p_gradient(env, theta, k_harvester_soil),
            ln_q_gradient(env, theta, k_harvester_soil),
        ),
        (stay, 2 * ln_p_gradient(env, theta, k_plow_soil), np.zeros(model.num_parameters)),
    ]
    for observed, authors, exact in cases:
        value, gradient = model.transition_log_likelihood(theta, [observed], rule="authors")
        exact_value, exact_gradient = model.transition_log_likelihood(theta, [observed])
        assert value == exact_value
        assert np.allclose(gradient, authors, atol=1e-7)
        assert np.allclose(exact_gradient, exact, atol=1e-7)


def test_the_authors_farming_update_through_the_planner() -> None:
    """Pulled back from dL/dT, each parametric entry e adds w_e * 2 d ln p (a success) or
    w_e * (d ln(1 - p) - d ln p) (a failure), w_e = dL/dT_e * T_e."""
    env = domains.make("two-fields")
    model = env.model
    rng = np.random.default_rng(3)
    theta = rng.normal(size=model.num_parameters)
    d_t = rng.normal(size=model.next_states.shape)
    table = model.probabilities(theta)
    gradients_p = {k: ln_p_gradient(env, theta, k) for k in range(model.num_parameters)}
    gradients_q = {k: ln_q_gradient(env, theta, k) for k in range(model.num_parameters)}
    expected = np.zeros(model.num_parameters)
    for s, a, m in zip(*np.nonzero(model.parametric_entries), strict=True):
        k = int(model.index[s, a, m])
        w = d_t[s, a, m] * table[s, a, m]
        if model.outcomes[s, a, m] > 0:
            expected += w * 2 * gradients_p[k]
        else:
            expected += w * (gradients_q[k] - gradients_p[k])
    assert np.allclose(model.pullback(theta, d_t, rule="authors"), expected, atol=1e-6)
    # The exact rule is the gradient of sum(d_t * T).
    exact = central_difference(lambda t: float((d_t * model.probabilities(t)).sum()), theta)
    assert np.allclose(model.pullback(theta, d_t), exact, atol=1e-6)


@pytest.mark.parametrize("name", ["doorway", "flip"])
def test_the_authors_rule_is_the_exact_gradient_outside_farming(name: str) -> None:
    env = domains.make(name)
    rng = np.random.default_rng(4)
    theta = rng.normal(size=env.model.num_parameters)
    d_t = rng.normal(size=env.model.next_states.shape)
    assert np.array_equal(
        env.model.pullback(theta, d_t, rule="authors"), env.model.pullback(theta, d_t)
    )


def test_bam_uses_the_authors_farming_update_by_default_and_exact_as_a_setting() -> None:
    _, authors = farming_learner("bam", alternations=1, cost_steps=2, dynamics_steps=3)
    _, exact = farming_learner(
        "bam", alternations=1, cost_steps=2, dynamics_steps=3, dynamics_gradient="exact"
    )
    assert not np.array_equal(authors.theta, exact.theta)
    with pytest.raises(ValueError, match="dynamics_gradient"):
        make_learner("bam", domains.make("two-fields"), dynamics_gradient="nearly")


# -- cloning and the action model -----------------------------------------------------------


def test_cloning_clips_its_table_to_three_and_has_an_optimiser_per_task() -> None:
    env = domains.make("wall")
    learner = make_learner("cloning", env, learning_rate=10.0, max_step=100.0, steps=50)
    for _ in range(20):
        learner.record_demonstration(0, env.state_of(6, 0), UP, env.state_of(5, 0))
    learner.update()
    assert learner.table.max() == 3.0 and learner.table.min() >= -3.0
    assert learner.optimizer.rows == len(env.tasks)


def test_cloning_breaks_only_exact_ties() -> None:
    env = domains.make("wall")
    learner = make_learner("cloning", env)
    state = env.state_of(6, 0)
    learner.record_demonstration(0, state, UP, env.state_of(5, 0))
    learner.table[0, state] = [0.0, 1.0, 1.0 - 1e-12, 0.0, 0.0]
    assert learner.policy(0)[state].tolist() == [0.0, 1.0, 0.0, 0.0, 0.0]
    tolerant = make_learner("cloning", env, tie_tolerance=1e-9)
    tolerant.record_demonstration(0, state, UP, env.state_of(5, 0))
    tolerant.table[0, state] = learner.table[0, state]
    assert tolerant.policy(0)[state].tolist() == [0.0, 0.5, 0.5, 0.0, 0.0]


def test_the_normalised_action_model_divides_by_one_only_where_a_row_is_flat() -> None:
    flat = np.zeros((1, 1, 5))
    value, _ = demonstration_log_likelihood(flat, [0], [0], [2], ActionModel())
    assert value == pytest.approx(np.log(1 / 5))
    # A nearly flat row is normalised by its own deviation (no floor): sd = 0.4e-12, so the
    # larger action's logit is 2.5; with a floor of 1e-8 the row is as good as flat.
    tiny = np.array([[[0.0, 1e-12, 0.0, 0.0, 0.0]]])
    value, _ = demonstration_log_likelihood(tiny, [0], [0], [1], ActionModel())
    floored, _ = demonstration_log_likelihood(tiny, [0], [0], [1], ActionModel(variance_floor=1e-8))
    assert value == pytest.approx(2.5 - np.log(np.exp(2.5) + 4), rel=1e-9)
    assert floored == pytest.approx(np.log(1 / 5), abs=1e-3)


# -- the gravity rule and the return --------------------------------------------------------


def test_a_colour_acts_when_the_agent_acts_from_its_cell() -> None:
    """Flip: orange sets gravity SOUTH, which forbids UP. Entering an orange cell keeps the
    gravity; any action from it (STAY included) first sets SOUTH, then is judged by it."""
    env = domains.make("flip")
    dense = env.transition_probabilities()
    north, south = GRAVITIES.index("north"), GRAVITIES.index("south")
    assert FORBIDDEN[south] == UP
    orange = (0, 1)
    below = env.state_of(1, 1, north)
    entered = env.state_of(*orange, north)
    assert dense[below, UP, entered] == 1.0  # entering: gravity unchanged
    assert dense[entered, STAY, env.state_of(*orange, south)] == 1.0
    assert dense[entered, DOWN, env.state_of(1, 1, south)] == 1.0
    assert dense[entered, LEFT, env.state_of(0, 0, south)] == 1.0
    assert dense[env.state_of(*orange, south), UP, env.state_of(*orange, south)] == 1.0


@pytest.mark.parametrize(
    ("name", "authors_expert"),
    [("doorway", 129.20), ("three-rooms", 84.69), ("wall", 52.97), ("two-rooms", 94.22)],
)
def test_optimal_totals_count_the_rewards_after_each_transition(
    name: str, authors_expert: float
) -> None:
    """Counting r(s_1) ... r(s_H), as the authors do, our optimal totals equal their expert's
    sampled returns (within their sampling noise, 0.5%)."""
    assert optimal_returns(domains.make(name)).sum() == pytest.approx(authors_expert, rel=5e-3)


def test_cloning_keeps_a_variance_floor_and_does_not_collapse() -> None:
    """Without a floor our cloning's rows shrink under the prior and the agent collapses from
    round 3 in doorway, which the authors' cloning does not: cloning keeps the floor (the
    planner learners use the authors' rule)."""
    from server.learners.evaluation import normalized_return
    from tests.learners._support import demonstrate_round

    env = domains.make("doorway")
    assert make_learner("cloning", env).settings.variance_floor == 1e-8
    assert make_learner("bam", env).settings.variance_floor == 0.0
    returns, deviations = {}, {}
    for floor in (1e-8, 0.0):
        learner = make_learner("cloning", env, seed=0, variance_floor=floor)
        teacher, rng = Teacher(env, seed=0), np.random.default_rng(0)
        for round_ in range(3):
            demonstrate_round(learner, env, teacher, rng)
            learner.update()
            if round_ == 0:
                # The cause: the prior shrinks the demonstrated rows, which the normalised
                # model cannot see, until only the floor holds their deviation up.
                demos = learner.data.demonstrations
                rows = learner.table[demos[:, 0], demos[:, 1]]
                deviations[floor] = float(np.median(rows.std(axis=1)))
        returns[floor] = normalized_return(env, learner)
    assert deviations[1e-8] > 1e-3 and deviations[0.0] < 1e-4
    assert returns[1e-8] > 0.6 and returns[0.0] < 0.2
