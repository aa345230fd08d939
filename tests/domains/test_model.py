"""The learner's dynamics model space T_theta on every environment: valid probabilities,
contains the true dynamics, and its log-likelihood and pull-back gradients are right."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from server import domains
from server.domains import farming, gravity, navigation
from server.domains.base import NUM_ACTIONS, Environment, SigmoidModel, SoftmaxRowsModel

H = 1e-6  # central finite-difference step


def random_theta(env: Environment, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).normal(0.0, 1.5, env.model.num_parameters)


def finite_difference(function: Callable[[np.ndarray], float], theta: np.ndarray) -> np.ndarray:
    gradient = np.empty_like(theta)
    for i in range(len(theta)):
        step = np.zeros_like(theta)
        step[i] = H
        gradient[i] = (function(theta + step) - function(theta - step)) / (2 * H)
    return gradient


def sample_observed(env: Environment, theta: np.ndarray, seed: int, count: int = 60) -> np.ndarray:
    """Observed (s, a, s') rows drawn from the model's support at theta, two thirds of them
    from rows that depend on theta."""
    rng = np.random.default_rng(seed)
    probabilities = env.model.probabilities(theta)
    parametric = np.argwhere((env.model.coef != 0).any(axis=2))
    rows = []
    for k in range(count):
        if k % 3:
            s, a = parametric[rng.integers(len(parametric))]
        else:
            s, a = rng.integers(env.num_states), rng.integers(NUM_ACTIONS)
        p = probabilities[s, a]
        m = rng.choice(len(p), p=p / p.sum())
        rows.append((s, a, env.model.next_states[s, a, m]))
    return np.asarray(rows, dtype=np.int64)


def assert_valid(env: Environment, theta: np.ndarray) -> None:
    sparse = env.model.probabilities(theta)
    assert sparse.shape == env.model.next_states.shape
    assert np.all(sparse >= 0.0)
    np.testing.assert_allclose(sparse.sum(axis=2), 1.0, rtol=0, atol=1e-12)
    dense = env.model.transitions(theta).dense()
    assert dense.shape == (env.num_states, NUM_ACTIONS, env.num_states)
    assert np.all(dense >= 0.0)
    np.testing.assert_allclose(dense.sum(axis=2), 1.0, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", domains.NAMES)
def test_model_probabilities_valid(name: str) -> None:
    env = domains.make(name)
    assert_valid(env, env.model.initial_parameters())
    for seed in range(3):
        assert_valid(env, random_theta(env, seed) * 4)


@pytest.mark.parametrize("name", domains.NAMES)
def test_model_space(name: str) -> None:
    """Parameter count, names and initialisation as the reference specifies."""
    env = domains.make(name)
    model = env.model
    assert len(model.parameter_names) == model.num_parameters
    if env.domain == "navigation":
        assert isinstance(model, SigmoidModel)
        assert model.num_parameters == env.num_cells and model.width == 2
        assert model.initial_value == -3.0
        assert model.parameter_names[env.width + 2] == "fail(1,2)"
        assert model.prior_sd is None and model.parameter_bound is None
    elif env.domain == "gravity":
        assert isinstance(model, SoftmaxRowsModel)
        colours = list(env.layout["gravity_of_colour"])
        assert colours == [c for c in ("orange", "green", "purple") if c in colours]
        assert (model.groups, model.choices, model.width) == (len(colours), 4, 4)
        assert model.parameter_names[:5] == (
            *(f"{colours[0]}->{g}" for g in ("north", "south", "east", "west")),
            f"{colours[1]}->north",
        )
        assert model.initial_value == 0.0
        assert model.prior_sd == 1.0 and model.parameter_bound == 50.0
    else:
        assert isinstance(model, SoftmaxRowsModel)
        # The authors' four terrains, dirt included, without prior, clipped to +-50.
        assert (model.groups, model.choices, model.width) == (3, 4, 2)
        assert model.parameter_names == tuple(
            f"{m}->{t}"
            for m in ("plow", "sprinkler", "harvester")
            for t in ("dirt", "soil", "grass", "crops")
        )
        assert model.initial_value == 0.0
        assert model.prior_sd is None and model.parameter_bound == 50.0
    assert np.all(model.initial_parameters() == model.initial_value)


@pytest.mark.parametrize("name", domains.NAMES)
def test_true_model_parameters_reproduce_true_dynamics(name: str) -> None:
    env = domains.make(name)
    theta = domains.true_model_parameters(env)
    module = {"navigation": navigation, "gravity": gravity, "farming": farming}[env.domain]
    assert np.array_equal(theta, module.true_model_parameters(env))
    assert theta.shape == (env.model.num_parameters,)
    np.testing.assert_allclose(
        env.model.probabilities(theta), env.true_transitions.probabilities, rtol=0, atol=1e-9
    )
    np.testing.assert_allclose(
        env.model.transitions(theta).dense(), env.transition_probabilities(), rtol=0, atol=1e-9
    )
    # The initial model is far from the truth somewhere: there is something to learn.
    initial = env.model.probabilities(env.model.initial_parameters())
    assert np.abs(initial - env.true_transitions.probabilities).max() > 0.5


@pytest.mark.parametrize("name", ["wall", "flip", "two-fields"])
def test_true_model_parameters_reject_other_domains(name: str) -> None:
    env = domains.make(name)
    for module in (navigation, gravity, farming):
        if module.DOMAIN != env.domain:
            with pytest.raises(ValueError, match="not"):
                module.true_model_parameters(env)


@pytest.mark.parametrize("name", domains.NAMES)
def test_true_transitions_in_model_support(name: str) -> None:
    """Every true transition is possible in the model space (a learner can observe it)."""
    env = domains.make(name)
    successors = env.transition_probabilities().argmax(axis=2)
    states = np.repeat(np.arange(env.num_states), NUM_ACTIONS)
    actions = np.tile(np.arange(NUM_ACTIONS), env.num_states)
    observed = np.stack([states, actions, successors.ravel()], axis=1)
    value, gradient = env.model.transition_log_likelihood(env.model.initial_parameters(), observed)
    assert np.isfinite(value) and np.all(np.isfinite(gradient))
    # Under the true parameters the true transitions are (numerically) certain.
    value, _ = env.model.transition_log_likelihood(domains.true_model_parameters(env), observed)
    assert -1e-9 < value <= 0.0


@pytest.mark.parametrize("name", domains.NAMES)
def test_transition_log_likelihood_gradient(name: str) -> None:
    env = domains.make(name)
    theta = random_theta(env, 1)
    observed = sample_observed(env, theta, seed=2)
    value, gradient = env.model.transition_log_likelihood(theta, observed)
    probabilities = env.model.probabilities(theta)
    match = env.model.next_states[observed[:, 0], observed[:, 1]] == observed[:, 2:3]
    expected_value = np.log((probabilities[observed[:, 0], observed[:, 1]] * match).sum(1)).sum()
    assert value == pytest.approx(expected_value, rel=1e-12)
    numeric = finite_difference(
        lambda t: env.model.transition_log_likelihood(t, observed)[0], theta
    )
    assert np.abs(gradient).max() > 1e-3
    np.testing.assert_allclose(gradient, numeric, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("name", domains.NAMES)
def test_pullback_gradient(name: str) -> None:
    env = domains.make(name)
    theta = random_theta(env, 3)
    weights = np.random.default_rng(4).normal(size=env.model.next_states.shape)
    gradient = env.model.pullback(theta, weights)
    numeric = finite_difference(
        lambda t: float((weights * env.model.probabilities(t)).sum()), theta
    )
    np.testing.assert_allclose(gradient, numeric, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("name", ["doorway", "choices", "three-fields"])
def test_pullback_dense_gradient(name: str) -> None:
    env = domains.make(name)
    theta = random_theta(env, 5)
    weights = np.random.default_rng(6).normal(size=(env.num_states, NUM_ACTIONS, env.num_states))
    gradient = env.model.pullback_dense(theta, weights)
    numeric = finite_difference(
        lambda t: float((weights * env.model.transitions(t).dense()).sum()), theta
    )
    np.testing.assert_allclose(gradient, numeric, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("name", domains.ENVIRONMENTS)
def test_observed_transitions_matched_once_give_the_same_likelihood(name: str) -> None:
    """A learner matches its observed transitions to the table once per update (observe) and
    evaluates them at many theta: the same value and gradient as the dense formula, where a
    row's next state may appear in several of its entries (a failed move that stays put)."""
    env = domains.make(name)
    observed = sample_observed(env, random_theta(env, 1), seed=2)
    prepared = env.model.observe(observed)
    assert env.model.observe(prepared) is prepared
    for seed in (3, 4):
        theta = random_theta(env, seed)
        value, gradient = env.model.transition_log_likelihood(theta, prepared)
        again, again_gradient = env.model.transition_log_likelihood(theta, observed)
        assert value == again
        np.testing.assert_array_equal(gradient, again_gradient)
        dense = env.model.transitions(theta).dense()
        expected = np.log(dense[observed[:, 0], observed[:, 1], observed[:, 2]]).sum()
        assert value == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("name", ["doorway", "flip", "two-fields"])
def test_the_kept_table_follows_theta_and_stays_the_model_s(name: str) -> None:
    """The model keeps its last theta's table and primitives: a theta changed in place gets
    its own table, each call returns an array of the caller's own, and the pull-back at a kept
    theta equals a fresh model's."""
    env = domains.make(name)
    model = env.model
    rng = np.random.default_rng(5)
    theta = model.initial_parameters() + rng.normal(size=model.num_parameters)
    first = model.probabilities(theta)
    first[...] = -1.0  # the caller's own array: the model's kept table is untouched
    again = model.probabilities(theta)
    assert np.all(again >= 0.0)
    theta[0] += 0.5  # the same array, another theta
    moved = model.probabilities(theta)
    fresh = domains.make(name).model
    np.testing.assert_array_equal(moved, fresh.probabilities(theta.copy()))
    assert not np.array_equal(moved, again)
    d_probabilities = rng.normal(size=model.next_states.shape)
    np.testing.assert_array_equal(
        model.pullback(theta, d_probabilities), fresh.pullback(theta.copy(), d_probabilities)
    )
    # The pull-back reads only the entries theta moves.
    frozen = d_probabilities.copy()
    frozen[~model.parametric_entries] = 1e6
    np.testing.assert_array_equal(
        model.pullback(theta, frozen), model.pullback(theta, d_probabilities)
    )


@pytest.mark.parametrize("name", ["three-fields", "flip", "wall"])
def test_a_model_restricted_to_the_states_it_can_reach(name: str) -> None:
    """``reachable`` closes a set of states under every entry some theta makes non-zero; the
    model restricted to such a set has, at any theta, the whole model's rows of those states,
    their next states renumbered, and refuses a set that is not closed."""
    env = domains.make(name)
    model = env.model
    start = np.array([env.sample_start(0, np.random.default_rng(0))])
    states = model.reachable(start)
    assert start[0] in states and np.all(np.diff(states) > 0)
    possible = (model.const != 0.0) | (model.coef != 0.0)
    assert np.isin(model.next_states[states][possible[states]], states).all()
    part = model.restricted(states)
    assert model.restricted(states) is part  # kept
    assert type(part) is type(model) and part.num_states == len(states)
    theta = model.initial_parameters() + np.random.default_rng(1).normal(size=model.num_parameters)
    whole_table, table = model.probabilities(theta), part.probabilities(theta)
    np.testing.assert_array_equal(table, whole_table[states])
    entries = table > 0.0
    np.testing.assert_array_equal(
        states[part.next_states][entries], model.next_states[states][entries]
    )
    if len(states) < model.num_states:
        with pytest.raises(ValueError, match="every state they can reach"):
            model.restricted(start if len(model.reachable(start)) > 1 else states[:-1])


def test_restricted_models_kept_are_bounded() -> None:
    """A model keeps at most RESTRICTIONS_KEPT restricted models (a long-running study server
    sees many sets of states); a dropped one is built again, equal to the first."""
    from server.domains.base import RESTRICTIONS_KEPT

    env = domains.make("three-fields")
    model = env.model
    rng = np.random.default_rng(2)
    sets = []
    while len(sets) < RESTRICTIONS_KEPT + 3:
        states = model.reachable(rng.integers(0, model.num_states, size=2))
        if not any(np.array_equal(states, known) for known in sets):
            sets.append(states)
    first = model.restricted(sets[0])
    for states in sets[1:]:
        model.restricted(states)
        assert len(model._restrictions) <= RESTRICTIONS_KEPT
    again = model.restricted(sets[0])
    theta = model.initial_parameters()
    np.testing.assert_array_equal(again.probabilities(theta), first.probabilities(theta))
    np.testing.assert_array_equal(again.next_states, first.next_states)
