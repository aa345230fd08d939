"""The planner: soft value iteration (equations (1)-(2)) and its reverse pass, hard-max value
iteration and exact expected returns, checked against hand values, brute force and finite
differences."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest

from server import domains
from server.domains.base import SparseTransitions
from server.learners import planning
from server.learners.planning import (
    TransitionOperator,
    expected_return,
    hard_value_iteration,
    soft_plan,
    soft_value_iteration,
    soft_value_iteration_backward,
)
from tests.learners._support import H, central_difference

# Perturbing one transition entry by h leaves its row summing to 1 +- h; the planner accepts
# rows within 1e-8 of 1, so entry-wise differences use a smaller step (rounding error about
# 1e-16 |L| / h stays far below the tolerance on these small problems).
ENTRY_H = 2e-9


def random_dense(rng: np.random.Generator, states: int, actions: int) -> np.ndarray:
    transitions = rng.dirichlet(np.full(states, 0.7), size=(states, actions))
    return transitions / transitions.sum(axis=2, keepdims=True)


def random_sparse(
    rng: np.random.Generator, states: int, actions: int, width: int
) -> SparseTransitions:
    next_states = rng.integers(0, states, size=(states, actions, width))
    probabilities = rng.dirichlet(np.ones(width), size=(states, actions))
    probabilities /= probabilities.sum(axis=2, keepdims=True)
    return SparseTransitions(next_states.astype(np.int64), probabilities)


def boltzmann_value(q: np.ndarray, beta: float) -> np.ndarray:
    """V(s) = sum_a pi(a|s) Q(s, a), pi proportional to exp(beta Q): a Boltzmann expectation."""
    z = np.exp(beta * (q - q.max(axis=-1, keepdims=True)))
    return (z / z.sum(axis=-1, keepdims=True) * q).sum(axis=-1)


def brute_force_soft_q(transitions: np.ndarray, reward: np.ndarray, beta: float, horizon: int):
    """Equations (1)-(2) written out with dense arrays, for (K, S) rewards."""
    q = np.repeat(reward[:, :, None], transitions.shape[1], axis=2)
    for _ in range(horizon - 1):
        q = reward[:, :, None] + np.einsum("sat,kt->ksa", transitions, boltzmann_value(q, beta))
    return q


# -- forward values --------------------------------------------------------------------------

# Two states, two actions: action 0 stays, action 1 switches state; reward (0, 1).
TWO_STATE = np.array([[[1.0, 0.0], [0.0, 1.0]], [[0.0, 1.0], [1.0, 0.0]]])
TWO_STATE_REWARD = np.array([0.0, 1.0])


@pytest.mark.parametrize("beta", [1.0, 2.0])
def test_two_state_example_by_hand(beta: float) -> None:
    q1 = soft_value_iteration(TWO_STATE, TWO_STATE_REWARD, beta, 1)
    np.testing.assert_array_equal(q1, [[0.0, 0.0], [1.0, 1.0]])  # Q_1 = r
    # V_1 = (0, 1) whatever the policy; Q_2(s, a) = r(s) + V_1(s').
    q2 = soft_value_iteration(TWO_STATE, TWO_STATE_REWARD, beta, 2)
    np.testing.assert_allclose(q2, [[0.0, 1.0], [2.0, 1.0]], rtol=0, atol=1e-14)
    # V_2(0) = (0 + 1 e^b) / (1 + e^b), V_2(1) = (2 e^2b + 1 e^b) / (e^2b + e^b).
    e = math.exp(beta)
    v0 = e / (1 + e)
    v1 = (2 * e * e + e) / (e * e + e)
    q3 = soft_value_iteration(TWO_STATE, TWO_STATE_REWARD, beta, 3)
    np.testing.assert_allclose(q3, [[v0, v1], [1 + v1, 1 + v0]], rtol=0, atol=1e-14)
    # A Boltzmann expectation, not log-sum-exp: log(1 + e^b)/b would exceed the max.
    assert v0 < 1.0


def test_horizon_one_is_the_reward() -> None:
    rng = np.random.default_rng(0)
    transitions = random_dense(rng, 5, 3)
    reward = rng.normal(size=(2, 5))
    q = soft_value_iteration(transitions, reward, 1.0, 1)
    np.testing.assert_array_equal(q, np.repeat(reward[:, :, None], 3, axis=2))


@pytest.mark.parametrize("beta", [0.5, 1.0, 3.0])
def test_backups_follow_equations_1_and_2(beta: float) -> None:
    """Q_{h+1} = r + T V_h with V_h the Boltzmann expectation of Q_h, for every h."""
    rng = np.random.default_rng(1)
    transitions = random_dense(rng, 6, 4)
    reward = rng.normal(size=(3, 6))
    previous = soft_value_iteration(transitions, reward, beta, 1)
    for horizon in range(2, 9):
        q = soft_value_iteration(transitions, reward, beta, horizon)
        expected = reward[:, :, None] + np.einsum(
            "sat,kt->ksa", transitions, boltzmann_value(previous, beta)
        )
        np.testing.assert_allclose(q, expected, rtol=1e-12, atol=1e-12)
        previous = q
    np.testing.assert_allclose(
        previous, brute_force_soft_q(transitions, reward, beta, 8), rtol=1e-12, atol=1e-12
    )


def test_several_tasks_equal_one_task_at_a_time() -> None:
    rng = np.random.default_rng(2)
    transitions = random_sparse(rng, 7, 5, 3)
    reward = rng.normal(size=(3, 7))
    q = soft_value_iteration(transitions, reward, 1.0, 6)
    assert q.shape == (3, 7, 5)
    for k in range(3):
        single = soft_value_iteration(transitions, reward[k], 1.0, 6)
        assert single.shape == (7, 5)
        np.testing.assert_allclose(single, q[k], rtol=1e-13, atol=1e-13)


def test_sparse_dense_and_operator_inputs_agree() -> None:
    rng = np.random.default_rng(3)
    sparse = random_sparse(rng, 8, 5, 3)
    dense = sparse.dense()
    reward = rng.normal(size=(2, 8))
    q_dense = soft_value_iteration(dense, reward, 1.5, 7)
    q_sparse = soft_value_iteration(sparse, reward, 1.5, 7)
    q_operator = soft_value_iteration(TransitionOperator(sparse), reward, 1.5, 7)
    np.testing.assert_allclose(q_sparse, q_dense, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(q_operator, q_dense, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(
        q_dense, brute_force_soft_q(dense, reward, 1.5, 7), rtol=1e-12, atol=1e-12
    )


def test_soft_values_never_exceed_hard_values() -> None:
    """A Boltzmann expectation is at most the max, so soft Q <= hard Q, approaching it as
    beta grows."""
    rng = np.random.default_rng(4)
    transitions = random_dense(rng, 6, 4)
    reward = rng.uniform(size=(2, 6))
    hard = hard_value_iteration(transitions, reward, 10)
    gaps = []
    for beta in (0.5, 2.0, 200.0):
        soft = soft_value_iteration(transitions, reward, beta, 10)
        assert np.all(soft <= hard + 1e-12)
        gaps.append(np.abs(hard - soft).max())
    assert gaps[0] > gaps[1] > gaps[2] and gaps[2] < 1e-2


# -- the reverse pass ------------------------------------------------------------------------


def sum_weighted_q(transitions, reward, beta, horizon, weights) -> float:
    return float((weights * soft_value_iteration(transitions, reward, beta, horizon)).sum())


def rebuild(template, probabilities: np.ndarray):
    if isinstance(template, SparseTransitions):
        return SparseTransitions(template.next_states, probabilities)
    return probabilities


def entries(transitions) -> np.ndarray:
    return transitions.probabilities if isinstance(transitions, SparseTransitions) else transitions


CASES = [
    # (form, several tasks, beta)
    ("dense", False, 1.0),
    ("dense", True, 1.0),
    ("dense", True, 2.5),
    ("sparse", False, 1.0),
    ("sparse", True, 0.5),
    ("sparse", True, 2.5),
]


def make_problem(form: str, several: bool, seed: int):
    rng = np.random.default_rng(seed)
    states, actions = 5, 4
    transitions = (
        random_dense(rng, states, actions)
        if form == "dense"
        else random_sparse(rng, states, actions, 3)
    )
    reward = rng.normal(size=(3, states) if several else (states,))
    weights = rng.normal(size=(*reward.shape, actions))
    return transitions, reward, weights


@pytest.mark.parametrize(("form", "several", "beta"), CASES)
def test_reward_gradient_matches_finite_differences(form: str, several: bool, beta: float) -> None:
    transitions, reward, weights = make_problem(form, several, seed=10)
    horizon = 6
    d_reward, _ = soft_plan(transitions, reward, beta, horizon).backward(weights)
    assert d_reward.shape == reward.shape
    numeric = central_difference(
        lambda r: sum_weighted_q(transitions, r.reshape(reward.shape), beta, horizon, weights),
        reward,
    )
    np.testing.assert_allclose(d_reward.ravel(), numeric, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize(("form", "several", "beta"), CASES)
def test_transition_gradient_matches_finite_differences(
    form: str, several: bool, beta: float
) -> None:
    """dL/dT with every entry a free variable (the form of the input: dense (S, A, S) or the
    sparse (S, A, M) probabilities)."""
    transitions, reward, weights = make_problem(form, several, seed=11)
    horizon = 6
    _, d_transitions = soft_plan(transitions, reward, beta, horizon).backward(weights)
    probabilities = entries(transitions)
    assert d_transitions is not None and d_transitions.shape == probabilities.shape

    def loss(p: np.ndarray) -> float:
        return sum_weighted_q(
            rebuild(transitions, p.reshape(probabilities.shape)), reward, beta, horizon, weights
        )

    numeric = central_difference(loss, probabilities, h=ENTRY_H)
    np.testing.assert_allclose(d_transitions.ravel(), numeric, rtol=1e-4, atol=2e-5)


@pytest.mark.parametrize(("form", "several", "beta"), CASES)
def test_transition_gradient_along_valid_directions(form: str, several: bool, beta: float) -> None:
    """Directional derivatives along perturbations that keep every row summing to 1 (the
    ones a dynamics model can make), with the usual step h = 1e-6."""
    transitions, reward, weights = make_problem(form, several, seed=12)
    horizon = 7
    _, d_transitions = soft_plan(transitions, reward, beta, horizon).backward(weights)
    probabilities = entries(transitions)
    rng = np.random.default_rng(13)
    for _ in range(6):
        direction = rng.normal(size=probabilities.shape)
        direction -= direction.mean(axis=2, keepdims=True)
        numeric = (
            sum_weighted_q(
                rebuild(transitions, probabilities + H * direction), reward, beta, horizon, weights
            )
            - sum_weighted_q(
                rebuild(transitions, probabilities - H * direction), reward, beta, horizon, weights
            )
        ) / (2 * H)
        assert float((d_transitions * direction).sum()) == pytest.approx(
            numeric, rel=1e-6, abs=1e-7
        )


def test_several_tasks_gradients_are_sums_of_single_task_gradients() -> None:
    transitions, reward, weights = make_problem("sparse", True, seed=14)
    d_reward, d_transitions = soft_plan(transitions, reward, 1.0, 5).backward(weights)
    total = np.zeros_like(d_transitions)
    for k in range(len(reward)):
        d_r, d_t = soft_plan(transitions, reward[k], 1.0, 5).backward(weights[k])
        np.testing.assert_allclose(d_r, d_reward[k], rtol=1e-12, atol=1e-12)
        total += d_t
    np.testing.assert_allclose(d_transitions, total, rtol=1e-12, atol=1e-12)


def test_sparse_gradient_is_the_dense_gradient_at_the_stored_entries() -> None:
    rng = np.random.default_rng(15)
    states, actions = 6, 3
    # Distinct next states per row, so every sparse entry is one dense entry.
    next_states = np.stack(
        [
            np.stack([rng.choice(states, size=3, replace=False) for _ in range(actions)])
            for _ in range(states)
        ]
    )
    sparse = SparseTransitions(next_states, rng.dirichlet(np.ones(3), size=(states, actions)))
    reward = rng.normal(size=(2, states))
    weights = rng.normal(size=(2, states, actions))
    _, d_sparse = soft_plan(sparse, reward, 1.0, 5).backward(weights)
    _, d_dense = soft_plan(sparse.dense(), reward, 1.0, 5).backward(weights)
    np.testing.assert_allclose(
        d_sparse, np.take_along_axis(d_dense, next_states, axis=2), rtol=1e-12, atol=1e-12
    )


def test_cost_only_reverse_pass_and_convenience_function() -> None:
    transitions, reward, weights = make_problem("dense", True, seed=16)
    full_reward, full_transitions = soft_plan(transitions, reward, 1.0, 5).backward(weights)
    cost_only, nothing = soft_plan(transitions, reward, 1.0, 5).backward(
        weights, need_transitions=False
    )
    assert nothing is None
    np.testing.assert_allclose(cost_only, full_reward, rtol=1e-13, atol=1e-13)
    d_reward, d_transitions = soft_value_iteration_backward(transitions, reward, 1.0, 5, weights)
    np.testing.assert_allclose(d_reward, full_reward, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(d_transitions, full_transitions, rtol=1e-13, atol=1e-13)
    # The plan's Q is the forward pass's Q.
    np.testing.assert_array_equal(
        soft_plan(transitions, reward, 1.0, 5).q, soft_value_iteration(transitions, reward, 1.0, 5)
    )


# (environment, planning horizon, scale of random dynamics parameters)
MODEL_CASES = [
    ("wall", None, 1.5),
    ("doorway", None, 1.5),
    ("two-fields", None, 1.0),
    ("flip", 30, 1.0),
]


@pytest.mark.parametrize(("name", "horizon", "scale"), MODEL_CASES)
def test_gradient_through_the_environment_model(
    name: str, horizon: int | None, scale: float
) -> None:
    """d/dtheta sum(W * Q(T_theta)) from the reverse pass pulled back through env.model equals
    finite differences in theta."""
    env = domains.make(name)
    horizon = horizon or env.horizon
    rng = np.random.default_rng(20)
    theta = env.model.initial_parameters() + rng.normal(0.0, scale, env.model.num_parameters)
    reward = rng.normal(0.0, 0.3, size=(2, env.num_states))
    weights = rng.normal(size=(2, env.num_states, env.num_actions)) / env.num_states

    def loss(parameters: np.ndarray) -> float:
        return sum_weighted_q(env.model.transitions(parameters), reward, 1.0, horizon, weights)

    plan = soft_plan(env.model.transitions(theta), reward, 1.0, horizon)
    _, d_probabilities = plan.backward(weights)
    analytic = env.model.pullback(theta, d_probabilities)
    numeric = central_difference(loss, theta)
    assert np.abs(analytic).max() > 1e-3  # the check is not vacuous
    np.testing.assert_allclose(analytic, numeric, rtol=1e-5, atol=1e-7)


# -- hard-max value iteration and expected returns -------------------------------------------


def chain() -> tuple[np.ndarray, np.ndarray]:
    """States 0 - 1 - 2 in a row; actions STAY, LEFT, RIGHT (moves off the end stay put);
    reward 1 at state 2."""
    transitions = np.zeros((3, 3, 3))
    for s in range(3):
        transitions[s, 0, s] = 1.0
        transitions[s, 1, max(s - 1, 0)] = 1.0
        transitions[s, 2, min(s + 1, 2)] = 1.0
    return transitions, np.array([0.0, 0.0, 1.0])


def test_hard_value_iteration_on_a_chain_by_hand() -> None:
    transitions, reward = chain()
    # Q_H(s, a): the most reward collected in H steps (the current state's reward counts).
    np.testing.assert_array_equal(
        hard_value_iteration(transitions, reward, 1), [[0, 0, 0], [0, 0, 0], [1, 1, 1]]
    )
    q4 = hard_value_iteration(transitions, reward, 4)
    # From 0: RIGHT reaches 1 then 2 at step 3 -> rewards 0, 0, 1, 1; STAY or LEFT waste a
    # step -> 0, 0, 0, 1. From 1: RIGHT -> 0, 1, 1, 1; STAY -> 0, 0, 1, 1; LEFT -> 0, 0, 0, 1.
    # From 2: STAY or RIGHT -> 4; LEFT -> 1 + (0, 1, 1) = 3.
    np.testing.assert_array_equal(q4, [[1, 1, 2], [2, 1, 3], [4, 3, 4]])
    several = hard_value_iteration(transitions, np.stack([reward, reward[::-1]]), 4)
    np.testing.assert_array_equal(several[0], q4)
    np.testing.assert_array_equal(several[1], q4[::-1][:, [0, 2, 1]])  # the mirrored chain


def test_expected_return_of_deterministic_policies() -> None:
    transitions, reward = chain()
    start = np.array([1.0, 0.0, 0.0])
    right = np.array([2, 2, 2])
    assert expected_return(transitions, right, reward, start, 4) == pytest.approx(2.0, abs=1e-14)
    assert expected_return(transitions, np.zeros(3, dtype=int), reward, start, 4) == 0.0
    one_hot = np.eye(3)[right]
    assert expected_return(transitions, one_hot, reward, start, 4) == pytest.approx(2.0, abs=1e-14)
    # The optimal value from the hard planner is the return of the greedy policy here.
    q = hard_value_iteration(transitions, reward, 4)
    assert expected_return(transitions, right, reward, start, 4) == pytest.approx(
        float(start @ q.max(axis=1))
    )


def test_expected_return_of_a_stochastic_policy_by_hand() -> None:
    # Two states; in state 0 switch with probability 1/2, in state 1 stay. From state 0 the
    # agent is in state 1 with probability 0, 1/2, 3/4 at steps 1, 2, 3: return 1.25.
    policy = np.array([[0.5, 0.5], [1.0, 0.0]])
    value = expected_return(TWO_STATE, policy, TWO_STATE_REWARD, np.array([1.0, 0.0]), 3)
    assert value == pytest.approx(1.25, abs=1e-14)


def brute_force_return(transitions, policy, reward, start, horizon) -> float:
    p_pi = np.einsum("sa,sat->st", policy, transitions)
    return float(sum(start @ np.linalg.matrix_power(p_pi, t) @ reward for t in range(horizon)))


@pytest.mark.parametrize("stochastic", [False, True])
def test_expected_return_matches_matrix_powers(stochastic: bool) -> None:
    rng = np.random.default_rng(30)
    states, actions = 9, 5
    transitions = random_dense(rng, states, actions)
    reward = rng.uniform(size=states)
    start = rng.dirichlet(np.ones(states))
    if stochastic:
        policy = rng.dirichlet(np.ones(actions), size=states)
    else:
        policy = np.eye(actions)[rng.integers(actions, size=states)]
    for horizon in (1, 2, 13):
        expected = brute_force_return(transitions, policy, reward, start, horizon)
        assert expected_return(transitions, policy, reward, start, horizon) == pytest.approx(
            expected, rel=1e-12
        )
        sparse = SparseTransitions.from_dense(transitions)
        assert expected_return(sparse, policy, reward, start, horizon) == pytest.approx(
            expected, rel=1e-12
        )
    if not stochastic:
        actions_only = policy.argmax(axis=1)
        assert expected_return(transitions, actions_only, reward, start, 13) == pytest.approx(
            brute_force_return(transitions, policy, reward, start, 13), rel=1e-12
        )


# -- bad input -------------------------------------------------------------------------------


def good_problem():
    rng = np.random.default_rng(40)
    return random_dense(rng, 4, 3), rng.normal(size=4)


@pytest.mark.parametrize(
    ("transitions", "match"),
    [
        (np.full((4, 3), 0.25), "shape"),
        (np.full((4, 3, 5), 0.2), "shape"),
        (np.full((4, 3, 4, 1), 0.25), "shape"),
    ],
)
def test_wrong_transition_shapes_are_rejected(transitions: np.ndarray, match: str) -> None:
    _, reward = good_problem()
    with pytest.raises(ValueError, match=match):
        soft_value_iteration(transitions, reward, 1.0, 3)
    with pytest.raises(ValueError, match=match):
        hard_value_iteration(transitions, reward, 3)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_transitions_or_rewards_are_rejected(bad: float) -> None:
    transitions, reward = good_problem()
    broken = transitions.copy()
    broken[1, 2, 3] = bad
    with pytest.raises(ValueError, match="NaN or infinite"):
        soft_value_iteration(broken, reward, 1.0, 3)
    with pytest.raises(ValueError, match="NaN or infinite"):
        hard_value_iteration(broken, reward, 3)
    sparse = SparseTransitions.from_dense(transitions)
    probabilities = sparse.probabilities.copy()
    probabilities[0, 0, 0] = bad
    with pytest.raises(ValueError, match="NaN or infinite"):
        soft_value_iteration(SparseTransitions(sparse.next_states, probabilities), reward, 1.0, 3)
    bad_reward = reward.copy()
    bad_reward[2] = bad
    with pytest.raises(ValueError, match="NaN or infinite"):
        soft_value_iteration(transitions, bad_reward, 1.0, 3)
    with pytest.raises(ValueError, match="NaN or infinite"):
        hard_value_iteration(transitions, bad_reward, 3)


def test_rows_not_summing_to_one_are_rejected() -> None:
    transitions, reward = good_problem()
    for change in (1e-4, -1e-4):
        broken = transitions.copy()
        broken[2, 1, 0] += change
        with pytest.raises(ValueError, match="sum"):
            soft_value_iteration(broken, reward, 1.0, 3)
        with pytest.raises(ValueError, match="sum"):
            hard_value_iteration(broken, reward, 3)
    negative = np.zeros((2, 1, 2))
    negative[:, 0] = [1.5, -0.5]
    with pytest.raises(ValueError, match="negative"):
        soft_value_iteration(negative, np.zeros(2), 1.0, 3)


def test_bad_sparse_tables_are_rejected() -> None:
    transitions, reward = good_problem()
    sparse = SparseTransitions.from_dense(transitions)
    out_of_range = sparse.next_states.copy()
    out_of_range[0, 0, 0] = 4
    with pytest.raises(ValueError, match="range"):
        soft_value_iteration(SparseTransitions(out_of_range, sparse.probabilities), reward, 1.0, 3)
    with pytest.raises(ValueError, match="shape"):
        soft_value_iteration(
            SparseTransitions(sparse.next_states[:, :, :2], sparse.probabilities), reward, 1.0, 3
        )


@pytest.mark.parametrize("reward_shape", [(5,), (2, 5), (2, 4, 1), ()])
def test_wrong_reward_shapes_are_rejected(reward_shape: tuple[int, ...]) -> None:
    transitions, _ = good_problem()
    with pytest.raises(ValueError, match="shape"):
        soft_value_iteration(transitions, np.zeros(reward_shape), 1.0, 3)
    with pytest.raises(ValueError, match="shape"):
        hard_value_iteration(transitions, np.zeros(reward_shape), 3)


@pytest.mark.parametrize("horizon", [0, -2, 2.5, "3", np.nan, np.inf])
def test_bad_horizons_are_rejected(horizon: float) -> None:
    transitions, reward = good_problem()
    with pytest.raises(ValueError, match="horizon"):
        soft_value_iteration(transitions, reward, 1.0, horizon)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="horizon"):
        hard_value_iteration(transitions, reward, horizon)  # type: ignore[arg-type]


@pytest.mark.parametrize("beta", [0.0, -1.0, np.nan, np.inf])
def test_bad_betas_are_rejected(beta: float) -> None:
    transitions, reward = good_problem()
    with pytest.raises(ValueError, match="beta"):
        soft_value_iteration(transitions, reward, beta, 3)


def test_bad_reverse_pass_input_is_rejected() -> None:
    transitions, reward = good_problem()
    plan = soft_plan(transitions, reward, 1.0, 3)
    for shape in [(4, 2), (1, 4, 3), (3, 4)]:
        with pytest.raises(ValueError, match="shape"):
            plan.backward(np.zeros(shape))
    for bad in (np.nan, np.inf):
        d_q = np.zeros((4, 3))
        d_q[1, 1] = bad
        with pytest.raises(ValueError, match="NaN or infinite"):
            plan.backward(d_q)
    several = soft_plan(transitions, np.stack([reward, reward]), 1.0, 3)
    with pytest.raises(ValueError, match="shape"):
        several.backward(np.zeros((4, 3)))


def test_bad_policies_are_rejected_by_expected_return() -> None:
    transitions, reward = chain()
    start = np.array([1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="range"):
        expected_return(transitions, np.array([0, 3, 1]), reward, start, 4)
    with pytest.raises(ValueError, match="range"):
        expected_return(transitions, np.array([0, -1, 1]), reward, start, 4)
    with pytest.raises(ValueError, match="shape"):
        expected_return(transitions, np.zeros((3, 2)), reward, start, 4)
    with pytest.raises(ValueError, match="NaN or infinite"):
        expected_return(transitions, np.full((3, 3), np.nan), reward, start, 4)
    with pytest.raises(ValueError, match="NaN or infinite"):
        expected_return(transitions, np.array([0, 1, 2]), reward, np.array([np.nan, 0, 1]), 4)


def test_compiled_exp_matches_numpy_on_the_weights_range() -> None:
    from server.learners._kernels import exp_nonpositive

    rng = np.random.default_rng(0)
    x = np.concatenate(
        [
            [0.0, -0.0, -1e-300, -0.5 * math.log(2), -math.log(2), -700.0, -708.0],
            -rng.exponential(5.0, size=4000),
            -rng.uniform(0.0, 1e-6, size=100),
            -rng.uniform(0.0, 708.0, size=1000),
        ]
    )
    out = np.empty_like(x)
    exp_nonpositive(x, out)
    assert out[0] == 1.0 and out[1] == 1.0  # the best action weighs exactly 1
    np.testing.assert_allclose(out, np.exp(x), rtol=4e-16, atol=0.0)
    # Below -708 the weight stays a tiny positive number, never a NaN or a negative one.
    deep = np.array([-709.0, -1e4, -np.inf])
    out = np.empty_like(deep)
    exp_nonpositive(deep, out)
    assert np.all((out >= 0.0) & (out <= 3.4e-308))


@pytest.mark.parametrize("actions", [5, 3])
def test_the_trace_holds_every_backups_value_and_jacobian(actions: int) -> None:
    """The reverse pass's trace: V_t is the Boltzmann value of Q_t and dV_t/dQ_t is
    pi_t (1 + beta (Q_t - V_t)) for t = 1 .. horizon - 1, nothing left unset (five actions take
    the compiled five-action code, three the general code)."""
    rng = np.random.default_rng(30)
    transitions = random_sparse(rng, 9, actions, 3)
    reward = rng.normal(size=(2, 9))
    beta, horizon = 1.5, 7
    plan = soft_plan(transitions, reward, beta, horizon)
    assert plan.values.shape == (horizon - 1, 2, 9)
    assert plan.value_jacobians.shape == (horizon - 1, 2, 9, actions)
    for t in range(1, horizon):
        q_t = soft_value_iteration(transitions, reward, beta, t)
        v_t = boltzmann_value(q_t, beta)
        np.testing.assert_allclose(plan.values[t - 1], v_t, rtol=1e-13, atol=1e-13)
        z = np.exp(beta * (q_t - q_t.max(axis=-1, keepdims=True)))
        pi = z / z.sum(axis=-1, keepdims=True)
        np.testing.assert_allclose(
            plan.value_jacobians[t - 1],
            pi * (1.0 + beta * (q_t - v_t[..., None])),
            rtol=1e-12,
            atol=1e-13,
        )
    again = soft_plan(transitions, reward, beta, horizon)
    np.testing.assert_array_equal(again.values, plan.values)
    np.testing.assert_array_equal(again.value_jacobians, plan.value_jacobians)


def test_five_action_code_computes_what_the_general_code_does() -> None:
    """The passes compiled for exactly five actions give the general code's numbers, bit for
    bit (the general code is called directly, with the action count as a run-time value: its
    loops not unrolled; the Boltzmann step, which takes its own code for five actions in both,
    is checked against the general one in the next test)."""
    from server.learners import _kernels

    env = domains.make("doorway")
    rng = np.random.default_rng(31)
    theta = env.model.initial_parameters() + rng.normal(size=env.model.num_parameters)
    op = TransitionOperator.build(env.model.transitions(theta))
    rewards = rng.normal(size=(len(env.tasks), env.num_states))
    tasks, horizon = len(env.tasks), env.horizon

    def forward(kernel, *five):  # type: ignore[no-untyped-def]
        trace = _kernels.Trace(
            np.empty((tasks, env.num_states, 5)),
            np.empty((horizon - 1, tasks, env.num_states)),
            np.empty((horizon - 1, tasks, 5, env.num_states)),  # by action, as the passes keep it
        )
        kernel(op.rows, rewards, 1.0, horizon, True, trace, 0, tasks, *five)
        return trace

    special, general = forward(_kernels.soft_forward_tasks), forward(_kernels._soft_forward, 5)
    for a, b in zip(special, general, strict=True):
        np.testing.assert_array_equal(a, b)
    d_q = rng.normal(size=special.q.shape)
    no_terms = np.empty((0, 0, 0))

    def backward(kernel, scatter, *chunk_and_the_rest):  # type: ignore[no-untyped-def]
        d_reward, d_probs = np.zeros((tasks, env.num_states)), np.zeros(op.next_flat.shape[0])
        gradient = _kernels.TableGradient(
            op.next_flat, op.width, op.gradient_entries, planning.NO_RUNS, planning.NO_ENTRIES,
            d_probs, no_terms, tasks, no_terms,
        )  # fmt: skip
        kernel(
            op.rows, op.incoming, scatter, special, d_q, horizon, d_reward, gradient,
            *chunk_and_the_rest,
        )  # fmt: skip
        return d_reward, d_probs

    # Both orders of summing dL/dV: the table's (float64 passes) and the forward layout's.
    for scatter in (False, True):
        # The public kernel slices the chunk's kept terms and task sums (none kept: all tasks
        # add at once); the general code is handed them.
        special_back = backward(_kernels.soft_backward_tasks, scatter, 0, tasks)
        general_back = backward(_kernels._soft_backward, scatter, no_terms, no_terms, 0, tasks, 5)
        for a, b in zip(special_back, general_back, strict=True):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("beta", [0.5, 1.0, 3.0])
def test_the_five_action_boltzmann_step_is_the_general_one_bit_for_bit(beta: float) -> None:
    """The forward pass's Boltzmann step for five actions (one loop over states, five exps
    interleaved) gives the general loops' weights and values to the last bit, the sign of a
    zero included: on ties, zeros of both signs, and rows far apart (weights near 0)."""
    from server.learners import _kernels

    rng = np.random.default_rng(32)
    num_states = 203  # not a multiple of a vector's width: the loops' remainders run too
    rows = rng.normal(scale=20.0, size=(5, num_states))
    rows[:, :10] = 1.25  # every action ties
    rows[2:4, 10:20] = rows[0, 10:20, None].T  # some tie with the first
    rows[:, 20:30] = rng.choice([0.0, -0.0], size=(5, 10))
    rows[:, 30:40] = rng.choice([0.0, -800.0, -1e4, 3.0], size=(5, 10))
    rows[:, 40:50] *= 1e-300
    rows = rows.ravel()  # row a * S + s, as the passes hold them
    five = (np.empty(5 * num_states), np.empty(num_states))
    general = (np.empty(5 * num_states), np.empty(num_states))
    _kernels._boltzmann_five(rows, beta, *five)
    _kernels._boltzmann(rows, beta, 5, general[0], np.empty(num_states), general[1])
    for a, b in zip(five, general, strict=True):
        np.testing.assert_array_equal(a.view(np.uint64), b.view(np.uint64))
    weights = five[0].reshape(5, num_states)
    np.testing.assert_allclose(weights.sum(axis=0), 1.0, rtol=1e-15)
    assert np.all(np.isfinite(five[1]))


@pytest.mark.parametrize("levels", [1, 3, 4, 5, 9])
def test_dense_levels_sum_each_state_s_terms_in_level_order(levels: int) -> None:
    """The reverse pass's dense levels, four to a loop, add each state's terms from zero in
    level order, as one loop per level does: checked to the last bit against Python's own
    float arithmetic, term by term (wall cells' padding included: probability 0)."""
    from server.learners import _kernels

    rng = np.random.default_rng(33)
    num_states = 37
    g = rng.normal(scale=10.0, size=5 * num_states)
    sources = rng.integers(0, g.shape[0], size=(levels, num_states))
    probabilities = rng.uniform(size=(levels, num_states))
    probabilities[rng.uniform(size=probabilities.shape) < 0.2] = 0.0
    g_v = np.full(num_states, np.nan)  # every state is written
    _kernels._dense_levels(g_v, sources, probabilities, g)
    for s in range(num_states):
        expected = 0.0
        for level in range(levels):
            expected = expected + float(probabilities[level, s]) * float(g[sources[level, s]])
        assert g_v[s] == expected, (s, g_v[s], expected)


@pytest.mark.parametrize("precision", ["float64", "float32"])
@pytest.mark.parametrize("backend", ["openmp", "python"])
@pytest.mark.parametrize("name", ["doorway", "two-rooms", "flip"])
def test_passes_split_over_threads_compute_the_same_bits(
    name: str, backend: str, precision: str, monkeypatch
) -> None:  # type: ignore[no-untyped-def]
    """A pass whose tasks are split over two or three threads gives the one-thread pass's
    numbers bit for bit (Q, the trace, and both gradients, the transition gradient summed
    over tasks in the one-thread order), with every entry's gradient and with the learners'
    narrowed entries, on OpenMP threads and on Python ones, in either precision; the thread
    count is restored afterwards."""
    if backend == "openmp" and not planning.compiled_threads():
        pytest.skip("no OpenMP runtime on this machine")
    if backend == "python":
        monkeypatch.setattr(planning, "_openmp", False)
    env = domains.make(name)
    rng = np.random.default_rng(33)
    theta = env.model.initial_parameters() + rng.normal(size=env.model.num_parameters)
    rewards = rng.normal(size=(len(env.tasks), env.num_states))
    d_q = rng.normal(size=(len(env.tasks), env.num_states, env.num_actions))
    operators = [
        TransitionOperator.build(env.model.transitions(theta)),
        TransitionOperator.of_model(env.model, theta),
    ]
    before = planning.planner_threads()
    results: dict[int, list[object]] = {}
    for threads in (1, 2, 3):
        results[threads] = []
        with planning.using_planner_threads(threads):
            for op in operators:
                plan = soft_plan(op, rewards, 0.8, env.horizon, precision=precision)
                d_reward, d_transitions = plan.backward(d_q)
                assert plan.values.dtype == precision
                results[threads] += [plan.q, plan.values, plan.value_jacobians, d_reward]
                results[threads] += [d_transitions]
    for threads in (2, 3):
        for one, split in zip(results[1], results[threads], strict=True):
            np.testing.assert_array_equal(split, one)
    assert np.any(results[1][-1] != 0.0)
    assert planning.planner_threads() == before


@pytest.mark.parametrize("precision", ["float64", "float32"])
@pytest.mark.parametrize("name", domains.NAMES)
def test_entries_summed_in_runs_have_the_gradient_of_entries_summed_alone(
    name: str, precision: str
) -> None:
    """A reverse pass that sums the moved entries' terms in runs of states (a SIMD loop over
    the states of one action and offset) gives every entry's gradient as summing each entry
    alone does, bit for bit, in every environment's model at a random theta; in the navigation
    environments, where the moved entries are moves to a neighbouring cell, runs hold most of
    them."""
    import dataclasses

    env = domains.make(name)
    rng = np.random.default_rng(35)
    theta = env.model.initial_parameters() + rng.normal(size=env.model.num_parameters)
    rewards = rng.normal(size=(len(env.tasks), env.num_states))
    d_q = rng.normal(size=(len(env.tasks), env.num_states, env.num_actions))
    op = TransitionOperator.of_model(env.model, theta)
    layout = op._layout
    assert layout is not None
    in_runs = soft_plan(op, rewards, 1.0, env.horizon, precision=precision).backward(d_q)
    op._layout = dataclasses.replace(layout, entry_runs=planning.NO_RUNS)
    alone = soft_plan(op, rewards, 1.0, env.horizon, precision=precision).backward(d_q)
    for a, b in zip(in_runs, alone, strict=True):
        np.testing.assert_array_equal(a, b)
    summed_in_runs = np.count_nonzero(layout.entry_slots >= 0)
    if name in ("wall", "doorway", "two-rooms", "three-rooms"):
        assert summed_in_runs > layout.entry_slots.shape[0] / 2
    assert np.any(alone[1] != 0.0)


@pytest.mark.parametrize("value", [0, -1, 1.5, "two", True, None])
def test_a_bad_planner_thread_count_is_refused(value: object, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """Zero, negative, fractional or non-numeric counts are refused with the setting's name,
    and leave the count as it was; the environment does not set it."""
    before = planning.planner_threads()
    with pytest.raises(ValueError, match="planner threads must be a positive integer"):
        planning.set_planner_threads(value)  # type: ignore[arg-type]
    assert planning.planner_threads() == before
    monkeypatch.setenv("BAM_PLANNER_THREADS", "2")
    assert planning.planner_threads() == before


def test_transition_gradient_only_where_asked() -> None:
    """``only_gradients_at`` (what the learners use: the entries theta moves) returns the full
    reverse pass's dL/dT at those entries and 0 elsewhere, so the gradient in theta is
    unchanged: to the last bit for one task; for two, to rounding (the whole table sums each
    task's terms before adding the tasks' sums, the narrowed pass adds them as they come). A
    mask of the wrong shape is refused."""
    env = domains.make("flip")
    rng = np.random.default_rng(32)
    theta = env.model.initial_parameters() + rng.normal(size=env.model.num_parameters)
    reward = rng.normal(0.0, 0.3, size=(2, env.num_states))
    d_q = rng.normal(size=(2, env.num_states, env.num_actions))
    full_op = TransitionOperator.build(env.model.transitions(theta))
    mask = env.model.parametric_entries
    narrow_op = TransitionOperator.build(env.model.transitions(theta)).only_gradients_at(mask)
    assert 0 < len(narrow_op.gradient_entries) < mask.size / 10  # flip: 216 of 8000
    for tasks in (slice(0, 1), slice(0, 2)):
        full_reward, full = soft_plan(full_op, reward[tasks], 1.0, 30).backward(d_q[tasks])
        narrow_reward, narrow = soft_plan(narrow_op, reward[tasks], 1.0, 30).backward(d_q[tasks])
        assert full is not None and narrow is not None
        np.testing.assert_array_equal(narrow_reward, full_reward)
        assert np.all(narrow[~mask] == 0.0) and np.any(full[~mask] != 0.0)
        narrow_theta = env.model.pullback(theta, narrow)
        full_theta = env.model.pullback(theta, full)
        if tasks.stop == 1:
            np.testing.assert_array_equal(narrow[mask], full[mask])
            np.testing.assert_array_equal(narrow_theta, full_theta)
        else:
            np.testing.assert_allclose(narrow[mask], full[mask], rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(narrow_theta, full_theta, rtol=1e-12, atol=1e-12)
            assert np.any(narrow[mask] != 0.0)
    with pytest.raises(ValueError, match="gradient mask must have shape"):
        full_op.only_gradients_at(np.ones((3, 3), dtype=bool))


@pytest.mark.parametrize("name", domains.ENVIRONMENTS)
def test_a_model_s_operator_is_the_checked_table_narrowed_to_its_parameters(name: str) -> None:
    """TransitionOperator.of_model (a learner's per-step table, built without re-checking)
    holds what the checked construction narrowed to the parametric entries holds, and a NaN
    parameter is still refused."""
    env = domains.make(name)
    theta = np.random.default_rng(5).normal(size=env.model.num_parameters) * 2.0
    fast = TransitionOperator.of_model(env.model, theta)
    checked = TransitionOperator.build(env.model.transitions(theta)).only_gradients_at(
        env.model.parametric_entries
    )
    for field in ("num_states", "num_actions", "width", "dense_input"):
        assert getattr(fast, field) == getattr(checked, field)
    for field in ("next_flat", "probs_flat", "gradient_entries"):
        np.testing.assert_array_equal(getattr(fast, field), getattr(checked, field))
    assert fast.matrix.toarray().tolist() == checked.matrix.toarray().tolist()
    theta[0] = np.nan
    with pytest.raises(ValueError, match="NaN or infinite"):
        TransitionOperator.of_model(env.model, theta)


@pytest.mark.parametrize("name", ["doorway", "flip", "two-fields"])
def test_a_model_s_pass_layouts_are_the_sorted_out_table_s(name: str) -> None:
    """A model's operators fill the passes' layouts kept for the model (its moved entries'
    pattern of zeros) instead of sorting the table out again: the same arrays as sorting out
    that theta's table, also when saturated parameters make moved entries exactly 0 and the
    pattern changes, and back."""
    from server.learners import _kernels

    env = domains.make(name)
    rng = np.random.default_rng(6)
    start = env.model.initial_parameters() + rng.normal(size=env.model.num_parameters)
    saturated = start.copy()
    saturated[1::2] = -800.0  # probabilities of exactly 0 (and 1)
    for theta in (start, start + 0.1, saturated, saturated + 0.1, start):
        operator = TransitionOperator.of_model(env.model, theta)
        layout = (operator.next_flat, operator.probs_flat, operator.width)
        sizes = (operator.num_states, operator.num_actions)
        expected = (*_kernels.split_rows(*layout, *sizes), *_kernels.incoming(*layout, *sizes))
        for got, want in zip((*operator.rows, *operator.incoming), expected, strict=True):
            np.testing.assert_array_equal(got, want)
    assert np.any(TransitionOperator.of_model(env.model, saturated).probs_flat == 0.0) and (
        np.count_nonzero(TransitionOperator.of_model(env.model, saturated).probs_flat)
        != np.count_nonzero(TransitionOperator.of_model(env.model, start).probs_flat)
    )


def test_pass_entries_keep_each_row_s_and_each_next_state_s_order() -> None:
    """``split_rows``: the first non-zero entry of every row, then the rows' second entries,
    third entries and so on, skipping zeros wherever they sit in a row, so that a forward pass
    adds each row's terms in the row's order; ``incoming`` likewise by next state, the levels
    that at least half the states have dense (padded with probability 0), the rest flat."""
    from server.learners import _kernels

    next_states = np.array([[3, 1, 2, 0], [2, 2, 2, 2], [0, 3, 1, 2], [1, 0, 3, 2]])
    probabilities = np.array(
        [[0.0, 0.5, 0.0, 0.5], [1.0, 0.0, 0.0, 0.0], [0.25, 0.25, 0.0, 0.5], [0.0, 0.0, 0.0, 1.0]]
    )
    # Four states, one action: the passes' rows are the table's. Every offset is a sixteenth of
    # four states or more, so every entry is in a shifted row: (action, offset, lo, hi), level by
    # level, offsets in increasing order.
    shifts, shifted_p, shift_start, flat_rows, _, _, flat_start = _kernels.split_rows(
        next_states.reshape(-1), probabilities.reshape(-1), 4, 4, 1
    )
    assert shift_start.tolist() == [0, 3, 5, 6] and flat_rows.size == 0
    assert flat_start.tolist() == [0, 0, 0, 0]
    # Level 1: row 2 -> 0 (offset -2), row 3 -> 2 (-1), rows 0 and 1 -> 1 and 2 (+1).
    # Level 2: row 0 -> 0 (0), row 2 -> 3 (+1). Level 3: row 2 -> 2 (0).
    assert shifts.tolist() == [
        [0, -2, 2, 3], [0, -1, 3, 4], [0, 1, 0, 2], [0, 0, 0, 1], [0, 1, 2, 3], [0, 0, 2, 3]
    ]  # fmt: skip
    assert shifted_p.tolist() == [
        [0, 0, 0.25, 0], [0, 0, 0, 1.0], [0.5, 1.0, 0, 0], [0.5, 0, 0, 0], [0, 0, 0.25, 0],
        [0, 0, 0.5, 0],
    ]  # fmt: skip
    # Reverse passes: by next state, every state's first entry in table order, then seconds...
    # States 0 and 2 have two or more entries (dense level 1), only state 2 a third (flat).
    dense_sources, dense_p, targets, sources, incoming_p = _kernels.incoming(
        next_states.reshape(-1), probabilities.reshape(-1), 4, 4, 1
    )
    assert dense_sources.tolist() == [[0, 0, 1, 2], [2, 0, 2, 0]]
    assert dense_p.tolist() == [[0.5, 0.5, 1.0, 0.25], [0.25, 0.0, 0.5, 0.0]]
    assert targets.tolist() == [2] and sources.tolist() == [3] and incoming_p.tolist() == [1.0]


def test_pass_rows_are_held_action_by_action() -> None:
    """The passes' row of (s, a) is a * S + s, in both directions: two states, two actions, the
    table's rows (s0, a0) -> 1, (s0, a1) -> 0, (s1, a0) -> 1, (s1, a1) -> 0."""
    from server.learners import _kernels

    next_states = np.array([1, 0, 1, 0])
    probabilities = np.ones(4)
    shifts, _, _, flat_rows, _, _, _ = _kernels.split_rows(next_states, probabilities, 1, 2, 2)
    # Action 0: state 1 stays (offset 0), state 0 moves to 1 (+1); action 1: state 1 moves to
    # 0 (-1), state 0 stays.
    assert shifts.tolist() == [[0, 0, 1, 2], [0, 1, 0, 1], [1, -1, 1, 2], [1, 0, 0, 1]]
    assert flat_rows.size == 0
    dense_sources, _, targets, _, _ = _kernels.incoming(next_states, probabilities, 1, 2, 2)
    # State 0 is reached from (s0, a1) and (s1, a1), rows 2 and 3; state 1 from rows 0 and 1.
    assert dense_sources.tolist() == [[2, 0], [3, 1]] and targets.size == 0
    # And the trace's Jacobians are kept by action, jacobians_by_action[t - 1, task, a, s]. With
    # r = (1, 0): V_1 = r, and Q_2 = (1, 2) in state 0, (0, 1) in state 1, so in both states
    # a1 is ahead by 1 and weighs p = e / (1 + e): dV_2/dQ_2 is (1 - p)^2 for a0 and
    # p (2 - p) for a1, in either state.
    plan = soft_plan(
        SparseTransitions(next_states.reshape(2, 2, 1), probabilities.reshape(2, 2, 1)),
        np.array([1.0, 0.0]),
        1.0,
        3,
    )
    p = math.e / (1.0 + math.e)
    np.testing.assert_allclose(
        plan.jacobians_by_action[1, 0], [[(1 - p) ** 2] * 2, [p * (2 - p)] * 2], rtol=1e-12
    )


def test_offsets_carried_by_few_states_are_gathered_not_shifted() -> None:
    """An offset that a sixteenth of the states or more take is a shifted row; the others are
    flat entries, each level's in the passes' row order: 32 states in a line, each moving one
    on, the last staying, state 5 jumping to 20 or moving on, half and half."""
    from server.learners import _kernels

    states = 32
    next_states = np.zeros((states, 2), dtype=np.int64)
    probabilities = np.zeros((states, 2))
    next_states[:, 0] = np.minimum(np.arange(states) + 1, states - 1)
    probabilities[:, 0] = 1.0
    next_states[5] = [20, 6]
    probabilities[5] = [0.5, 0.5]
    shifts, shifted_p, shift_start, flat_rows, flat_next, flat_p, flat_start = _kernels.split_rows(
        next_states.reshape(-1), probabilities.reshape(-1), 2, states, 1
    )
    # Level 1: offset +1 in 30 states (0 .. 30 but 5) is shifted; 5 -> 20 and 31 -> 31 are one
    # state each (fewer than 32 / 16): flat. Level 2: 5 -> 6, flat.
    assert shifts.tolist() == [[0, 1, 0, 31]] and shift_start.tolist() == [0, 1, 1]
    assert shifted_p[0].tolist() == [0.0 if s in (5, 31) else 1.0 for s in range(states)]
    assert flat_rows.tolist() == [5, 31, 5] and flat_next.tolist() == [20, 31, 6]
    assert flat_p.tolist() == [0.5, 1.0, 0.5] and flat_start.tolist() == [0, 2, 3]


@pytest.mark.parametrize("precision", ["float64", "float32"])
@pytest.mark.parametrize("name", domains.NAMES)
def test_forward_passes_add_each_row_s_terms_in_its_order(name: str, precision: str) -> None:
    """Q from the shifted rows and flat entries is, bit for bit, r plus each row's terms
    added in the table's order (the row's non-zero entries one after the other, in the passes'
    precision; float32 passes round each product and sum once, a fused multiply-add), after
    every number of backups, in every environment's model at a random theta."""
    env = domains.make(name)
    rng = np.random.default_rng(17)
    theta = env.model.initial_parameters() + rng.normal(size=env.model.num_parameters)
    operator = TransitionOperator.of_model(env.model, theta)
    dtype = np.dtype(precision).type
    rewards = rng.normal(size=(len(env.tasks), env.num_states))
    table = operator.probs_flat.reshape(env.num_states, env.num_actions, -1).astype(dtype)
    following = operator.next_flat.reshape(table.shape)
    for horizon in range(2, 7):
        plan = soft_plan(operator, rewards, 1.0, horizon, precision=precision)
        previous = plan.values[horizon - 2]  # V_{horizon - 1}, (tasks, S)
        expected = np.repeat(rewards.astype(dtype)[:, :, None], env.num_actions, axis=2)
        for m in range(table.shape[2]):
            p, v = table[None, :, :, m], previous[:, following[:, :, m]]
            if dtype == np.float32:
                # a * b + c rounded once: the product of two float32s is exact in x87's 64-bit
                # significand, the sum rounded there first (a second rounding that decides a
                # float32 result about once in 2^39).
                wide = np.longdouble
                added = (expected.astype(wide) + p.astype(wide) * v.astype(wide)).astype(dtype)
            else:
                added = expected + p * v
            expected = np.where(p != 0.0, added, expected)
        assert expected.dtype == dtype
        np.testing.assert_array_equal(plan.q_all, expected)


def _split_pass_in_child(queue) -> None:  # type: ignore[no-untyped-def]
    env = domains.make("flip")
    rewards = np.random.default_rng(34).normal(size=(len(env.tasks), env.num_states))
    result = soft_value_iteration(
        env.model.transitions(env.model.initial_parameters()), rewards, 1.0, env.horizon
    )
    queue.put((result, planning.compiled_threads(), planning._pool is not None))


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork")
@pytest.mark.parametrize("backend", ["openmp", "python"])
def test_a_forked_child_splits_passes_over_threads_of_its_own(backend: str, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    """A process forked after its parent's planner started its threads inherits neither the
    Python pool's threads nor a working OpenMP runtime (GNU OpenMP aborts a forked child's
    parallel loop): it must split its passes over Python threads of its own, not wait forever
    on a pool no thread serves or abort."""
    import multiprocessing

    if backend == "openmp" and not planning.compiled_threads():
        pytest.skip("no OpenMP runtime on this machine")
    if backend == "python":
        monkeypatch.setattr(planning, "_openmp", False)
    env = domains.make("flip")
    rewards = np.random.default_rng(34).normal(size=(len(env.tasks), env.num_states))
    with planning.using_planner_threads(2):
        expected = soft_value_iteration(
            env.model.transitions(env.model.initial_parameters()), rewards, 1.0, env.horizon
        )
        if backend == "python":
            assert planning._pool is not None  # the parent's threads exist
        context = multiprocessing.get_context("fork")
        queue = context.Queue()
        child = context.Process(target=_split_pass_in_child, args=(queue,))
        child.start()
        try:
            result, child_openmp, child_pool = queue.get(timeout=60)
            child.join(timeout=60)
        finally:
            if child.is_alive():
                child.kill()
    assert child.exitcode == 0
    np.testing.assert_array_equal(result, expected)
    assert not child_openmp and child_pool  # the child split its pass over Python threads


def test_entries_of_a_row_with_the_same_next_state_share_their_gradient() -> None:
    """A whole table's reverse pass computes each (row, next state) once and copies it to the
    row's other entries that lead there (padding, mostly): the gradient is the one computed
    entry by entry, to the last bit, and the copies are found."""
    rng = np.random.default_rng(35)
    transitions = random_sparse(rng, 9, 5, 3)
    transitions.next_states[4, 2] = [7, 7, 1]  # two entries of one row lead to state 7
    op = TransitionOperator.build(transitions)
    _, copies, originals = op.distinct_entries
    row = (4 * 5 + 2) * 3
    assert row + 1 in copies.tolist() and originals[copies.tolist().index(row + 1)] == row
    rewards = rng.normal(size=(2, 9))
    d_q = rng.normal(size=(2, 9, 5))
    shared = soft_plan(op, rewards, 1.2, 6).backward(d_q)[1]
    each = TransitionOperator.build(transitions)
    everything = each.gradient_entries
    each._distinct = (everything, everything, np.empty((2, 0), dtype=np.int64))
    separate = soft_plan(each, rewards, 1.2, 6).backward(d_q)[1]
    assert shared is not None and separate is not None
    np.testing.assert_array_equal(shared, separate)
    assert shared[4, 2, 0] == shared[4, 2, 1] != 0.0
