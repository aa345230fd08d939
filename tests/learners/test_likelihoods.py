"""Log-likelihoods of teacher data given Q: the Boltzmann action model (plain and normalised),
A-SABL feedback (equations (3)-(4)) and the Gaussian prior, against direct formulas and
finite differences."""

from __future__ import annotations

import math

import numpy as np
import pytest

from server.learners.likelihoods import (
    ActionModel,
    FeedbackModel,
    data_log_likelihood,
    demonstration_log_likelihood,
    feedback_log_likelihood,
    gaussian_log_prior,
)
from tests.learners._support import central_difference


def sigmoid(x: float) -> float:
    return 1.0 / (1.0 + math.exp(-x))


def log_softmax(logits: np.ndarray) -> np.ndarray:
    shifted = logits - logits.max()
    return shifted - math.log(float(np.exp(shifted).sum()))


# One task, two states, five actions.
Q = np.array([[[0.0, 1.0, 2.0, -1.0, 0.5], [3.0, 3.0, 1.0, 0.0, 2.0]]])


# -- demonstrated actions ----------------------------------------------------------------------


@pytest.mark.parametrize("beta", [1.0, 2.0])
def test_plain_action_model_by_hand(beta: float) -> None:
    value, _ = demonstration_log_likelihood(Q, [0], [0], [2], ActionModel(beta, normalized=False))
    row = Q[0, 0]
    expected = beta * 2.0 - math.log(sum(math.exp(beta * q) for q in row))
    assert value == pytest.approx(expected, abs=1e-12)


@pytest.mark.parametrize("beta", [1.0, 0.5])
def test_normalised_action_model_by_hand(beta: float) -> None:
    """p(a|s) proportional to exp(beta (Q(s,a) - Q(s,STAY)) / std_a Q(s,.))."""
    value, _ = demonstration_log_likelihood(Q, [0, 0], [0, 1], [2, 4], ActionModel(beta, True))
    expected = 0.0
    for state, action in ((0, 2), (1, 4)):
        row = Q[0, state]
        logits = beta * (row - row[0]) / row.std()
        expected += log_softmax(logits)[action]
    assert value == pytest.approx(expected, abs=1e-7)
    # Scale invariance: multiplying Q by a constant leaves the normalised model unchanged
    # (it is what keeps the model meaningful as Q grows with the horizon); the plain one is not.
    scaled, _ = demonstration_log_likelihood(
        10 * Q, [0, 0], [0, 1], [2, 4], ActionModel(beta, True)
    )
    assert scaled == pytest.approx(value, abs=1e-6)
    plain, _ = demonstration_log_likelihood(Q, [0, 0], [0, 1], [2, 4], ActionModel(beta, False))
    plain_scaled, _ = demonstration_log_likelihood(
        10 * Q, [0, 0], [0, 1], [2, 4], ActionModel(beta, False)
    )
    assert abs(plain - plain_scaled) > 1.0


def test_sum_over_rows_and_empty_data() -> None:
    model = ActionModel(1.0, True)
    both, _ = demonstration_log_likelihood(Q, [0, 0], [0, 1], [2, 4], model)
    first, _ = demonstration_log_likelihood(Q, [0], [0], [2], model)
    second, _ = demonstration_log_likelihood(Q, [0], [1], [4], model)
    assert both == pytest.approx(first + second, abs=1e-12)
    value, gradient = demonstration_log_likelihood(Q, [], [], [], model)
    assert value == 0.0 and gradient.shape == Q.shape and not gradient.any()


@pytest.mark.parametrize("normalized", [False, True])
def test_action_probabilities_sum_to_one(normalized: bool) -> None:
    rng = np.random.default_rng(0)
    q = rng.normal(0.0, 3.0, size=(2, 4, 5))
    model = ActionModel(1.3, normalized)
    for task in range(2):
        for state in range(4):
            total = sum(
                math.exp(demonstration_log_likelihood(q, [task], [state], [a], model)[0])
                for a in range(5)
            )
            assert total == pytest.approx(1.0, abs=1e-12)


def test_normalised_model_is_uniform_where_all_actions_are_equal() -> None:
    q = np.zeros((1, 1, 5))
    q[0, 0] = 2.5
    value, gradient = demonstration_log_likelihood(q, [0], [0], [3], ActionModel(1.0, True))
    assert value == pytest.approx(-math.log(5), abs=1e-12)
    assert np.all(np.isfinite(gradient))


@pytest.mark.parametrize(
    ("normalized", "beta"), [(False, 1.0), (False, 2.0), (True, 1.0), (True, 2.0)]
)
def test_action_gradient_matches_finite_differences(normalized: bool, beta: float) -> None:
    rng = np.random.default_rng(1)
    q = rng.normal(0.0, 2.0, size=(2, 4, 5))
    tasks = rng.integers(0, 2, 12)
    states = rng.integers(0, 4, 12)
    actions = rng.integers(0, 5, 12)
    model = ActionModel(beta, normalized)
    _, gradient = demonstration_log_likelihood(q, tasks, states, actions, model)

    def value(x: np.ndarray) -> float:
        return demonstration_log_likelihood(x.reshape(q.shape), tasks, states, actions, model)[0]

    numeric = central_difference(value, q)
    np.testing.assert_allclose(gradient.ravel(), numeric, rtol=1e-6, atol=1e-8)
    assert np.abs(gradient).max() > 0.1


# -- feedback (A-SABL) -------------------------------------------------------------------------


def a_sabl(delta: float, model: FeedbackModel) -> dict[int, float]:
    """Equations (3)-(4) written out."""
    positive = (1 - model.mu_plus) * (
        (1 - 2 * model.epsilon) * sigmoid(model.alpha * delta) + model.epsilon
    )
    negative = (1 - model.mu_minus) * (
        (1 - 2 * model.epsilon) * sigmoid(-model.alpha * delta) + model.epsilon
    )
    return {1: positive, -1: negative, 0: 1 - positive - negative}


FEEDBACK_MODELS = [
    FeedbackModel(),  # the reference settings: epsilon 0.05, alpha 1, mu+ = mu- = 0.1
    FeedbackModel(epsilon=0.2, alpha=2.5, mu_plus=0.3, mu_minus=0.05),
]


def test_reference_feedback_settings() -> None:
    model = FeedbackModel()
    assert (model.epsilon, model.alpha, model.mu_plus, model.mu_minus) == (0.05, 1.0, 0.1, 0.1)


@pytest.mark.parametrize("model", FEEDBACK_MODELS)
@pytest.mark.parametrize("feedback", [1, -1, 0])
def test_feedback_likelihood_by_hand(model: FeedbackModel, feedback: int) -> None:
    # State 0, action 2: advantage = Q(s, a) - mean_a Q(s, .) = 2 - 0.5 = 1.5.
    # State 1, action 3: advantage = 0 - 1.8 = -1.8.
    for state, action, delta in ((0, 2, 1.5), (1, 3, -1.8)):
        assert Q[0, state, action] - Q[0, state].mean() == pytest.approx(delta)
        value, _ = feedback_log_likelihood(Q, [0], [state], [action], [feedback], model)
        assert value == pytest.approx(math.log(a_sabl(delta, model)[feedback]), abs=1e-12)


@pytest.mark.parametrize("model", FEEDBACK_MODELS)
def test_feedback_probabilities_sum_to_one(model: FeedbackModel) -> None:
    rng = np.random.default_rng(2)
    q = rng.normal(0.0, 3.0, size=(1, 3, 5))
    for state in range(3):
        for action in range(5):
            total = sum(
                math.exp(feedback_log_likelihood(q, [0], [state], [action], [f], model)[0])
                for f in (1, -1, 0)
            )
            assert total == pytest.approx(1.0, abs=1e-12)


def test_feedback_prefers_good_actions() -> None:
    model = FeedbackModel()
    good, _ = feedback_log_likelihood(Q, [0], [0], [2], [1], model)  # advantage +1.5
    bad, _ = feedback_log_likelihood(Q, [0], [0], [3], [1], model)  # advantage -1.5
    assert good > bad
    good_minus, _ = feedback_log_likelihood(Q, [0], [0], [2], [-1], model)
    bad_minus, _ = feedback_log_likelihood(Q, [0], [0], [3], [-1], model)
    assert good_minus < bad_minus


@pytest.mark.parametrize("model", FEEDBACK_MODELS)
def test_feedback_gradient_matches_finite_differences(model: FeedbackModel) -> None:
    rng = np.random.default_rng(3)
    q = rng.normal(0.0, 2.0, size=(2, 4, 5))
    count = 15
    tasks = rng.integers(0, 2, count)
    states = rng.integers(0, 4, count)
    actions = rng.integers(0, 5, count)
    feedback = np.array([1, -1, 0] * 5)
    _, gradient = feedback_log_likelihood(q, tasks, states, actions, feedback, model)
    numeric = central_difference(
        lambda x: feedback_log_likelihood(
            x.reshape(q.shape), tasks, states, actions, feedback, model
        )[0],
        q,
    )
    np.testing.assert_allclose(gradient.ravel(), numeric, rtol=1e-6, atol=1e-8)
    assert np.abs(gradient).max() > 0.05


# -- the prior ---------------------------------------------------------------------------------


def test_gaussian_prior_value_and_gradient() -> None:
    rng = np.random.default_rng(4)
    x = rng.normal(size=7)
    value, gradient = gaussian_log_prior(x, 0.5, 2.0)
    assert value == pytest.approx(-0.5 * float(((x - 0.5) ** 2).sum()) / 4.0, abs=1e-12)
    numeric = central_difference(lambda p: gaussian_log_prior(p, 0.5, 2.0)[0], x)
    np.testing.assert_allclose(gradient, numeric, rtol=1e-7, atol=1e-9)
    mean = rng.normal(size=7)
    value, gradient = gaussian_log_prior(x, mean, 1.0)
    np.testing.assert_allclose(gradient, mean - x, rtol=1e-12)


# -- bad input ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("tasks", "states", "actions", "match"),
    [
        ([1], [0], [0], "task"),
        ([-1], [0], [0], "task"),
        ([0], [2], [0], "state"),
        ([0], [-1], [0], "state"),
        ([0], [0], [5], "action"),
        ([0], [0], [-1], "action"),
        ([0, 0], [0], [0], "length"),
        ([0], [0.5], [0], "state"),
        ([0], [0], [1.5], "action"),
    ],
    ids=[
        "task-too-large",
        "task-negative",
        "state-too-large",
        "state-negative",
        "action-too-large",
        "action-negative",
        "lengths-differ",
        "state-not-integer",
        "action-not-integer",
    ],
)
def test_bad_indices_are_rejected(tasks, states, actions, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        demonstration_log_likelihood(Q, tasks, states, actions, ActionModel())
    with pytest.raises(ValueError, match=match):
        feedback_log_likelihood(Q, tasks, states, actions, [1] * len(tasks), FeedbackModel())


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_q_is_rejected(bad: float) -> None:
    q = Q.copy()
    q[0, 1, 3] = bad
    for normalized in (False, True):
        with pytest.raises(ValueError, match="NaN or infinite"):
            demonstration_log_likelihood(q, [0], [0], [0], ActionModel(1.0, normalized))
    with pytest.raises(ValueError, match="NaN or infinite"):
        feedback_log_likelihood(q, [0], [0], [0], [1], FeedbackModel())
    with pytest.raises(ValueError, match="NaN or infinite"):
        gaussian_log_prior(np.array([0.0, bad]), 0.0, 1.0)


def test_q_of_the_wrong_shape_is_rejected() -> None:
    with pytest.raises(ValueError, match="shape"):
        demonstration_log_likelihood(Q[0], [0], [0], [0], ActionModel())
    with pytest.raises(ValueError, match="shape"):
        feedback_log_likelihood(Q[0], [0], [0], [0], [1], FeedbackModel())


@pytest.mark.parametrize("feedback", [2, -2, 5])
def test_feedback_outside_plus_minus_none_is_rejected(feedback: int) -> None:
    with pytest.raises(ValueError, match="feedback"):
        feedback_log_likelihood(Q, [0, 0], [0, 1], [0, 1], [1, feedback], FeedbackModel())
    with pytest.raises(ValueError, match="feedback"):
        feedback_log_likelihood(Q, [0], [0], [0], [1, 1], FeedbackModel())


def test_impossible_silence_is_an_error_not_minus_infinity() -> None:
    """With mu+ = mu- = 0 a teacher always gives feedback, so 'none' has probability 0."""
    model = FeedbackModel(mu_plus=0.0, mu_minus=0.0)
    with pytest.raises(ValueError, match="probability 0"):
        feedback_log_likelihood(Q, [0], [0], [0], [0], model)


@pytest.mark.parametrize(
    "settings",
    [
        {"epsilon": 0.5},
        {"epsilon": -0.1},
        {"alpha": 0.0},
        {"alpha": np.nan},
        {"mu_plus": 1.0},
        {"mu_minus": -0.2},
    ],
)
def test_bad_feedback_model_settings_are_rejected(settings: dict[str, float]) -> None:
    with pytest.raises(ValueError):
        FeedbackModel(**settings)


@pytest.mark.parametrize("beta", [0.0, -1.0, np.nan, np.inf])
def test_bad_action_model_beta_is_rejected(beta: float) -> None:
    with pytest.raises(ValueError, match="beta"):
        ActionModel(beta=beta)


@pytest.mark.parametrize("sd", [0.0, -1.0, np.nan])
def test_bad_prior_sd_is_rejected(sd: float) -> None:
    with pytest.raises(ValueError, match="standard deviation"):
        gaussian_log_prior(np.zeros(3), 0.0, sd)


# -- demonstrations and feedback in one compiled pass (what the learners' updates call) --------


def rows(*values: list[int]) -> list[np.ndarray]:
    return [np.array(v, dtype=np.int64) for v in values]


def random_data(
    rng: np.random.Generator, tasks: int, states: int, demos: int, steps: int, scale: float
) -> tuple[np.ndarray, list[np.ndarray], list[np.ndarray]]:
    """Q (tasks, states, 5), demonstration rows and agent-step rows with feedback."""
    q = rng.normal(size=(tasks, states, 5)) * scale
    demo = rows(
        rng.integers(0, tasks, demos), rng.integers(0, states, demos), rng.integers(0, 5, demos)
    )
    step_rows = rows(
        rng.integers(0, tasks, steps),
        rng.integers(0, states, steps),
        rng.integers(0, 5, steps),
        rng.integers(-1, 2, steps),
    )
    return q, demo, step_rows


@pytest.mark.parametrize("normalized", [False, True])
def test_one_pass_is_the_sum_of_the_two_likelihoods(normalized: bool) -> None:
    q, demo, steps = random_data(np.random.default_rng(3), 2, 6, 30, 25, scale=4.0)
    actions, feedback = ActionModel(1.5, normalized), FeedbackModel(alpha=0.8, epsilon=0.1)
    value, d_q = data_log_likelihood(q, *demo, actions, *steps, feedback)
    value_d, d_q_d = demonstration_log_likelihood(q, *demo, actions)
    value_f, d_q_f = feedback_log_likelihood(q, *steps, feedback)
    assert value == value_d + value_f
    np.testing.assert_array_equal(d_q, d_q_d + d_q_f)
    # ... and each part by hand, row by row.
    assert value_d == pytest.approx(
        sum(
            demonstration_log_likelihood(q, [k], [s], [a], actions)[0]
            for k, s, a in zip(*demo, strict=True)
        ),
        rel=1e-12,
    )


@pytest.mark.parametrize(
    ("demo", "steps", "match"),
    [
        (([2], [0], [0]), ([], [], [], []), "out of range"),
        (([0], [2], [0]), ([], [], [], []), "out of range"),
        (([0], [0], [-1]), ([], [], [], []), "out of range"),
        (([], [], []), ([0], [0], [5], [1]), "out of range"),
        (([], [], []), ([0], [-1], [0], [1]), "out of range"),
        (([], [], []), ([0], [0], [0], [3]), "feedback must be"),
    ],
)
def test_one_pass_refuses_bad_rows(demo, steps, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        data_log_likelihood(Q, *rows(*demo), ActionModel(), *rows(*steps), FeedbackModel())


def test_one_pass_refuses_non_finite_q() -> None:
    q = Q.copy()
    q[0, 0, 2] = np.nan
    with pytest.raises(FloatingPointError, match="not finite"):
        data_log_likelihood(q, *rows([0], [0], [1]), ActionModel(), *rows([], [], [], []))


# The C library's exp, log and pow, element by element, for the NumPy reference code below:
# NumPy's own run AVX-512 code on machines that have it (X86_V4), whose results differ from the
# C library's in the last bit for some arguments (4551 of 100,000 normal arguments of exp, 149
# of log; sd ** 3 in 15 of 300 rows here); the compiled pass calls the C library's on every
# machine, as NumPy does on machines without AVX-512. (The feedback model's tanh is NumPy's in
# both.)
libm_exp = np.vectorize(math.exp, otypes=[float])
libm_log = np.vectorize(math.log, otypes=[float])
libm_pow = np.vectorize(math.pow, otypes=[float])


def numpy_demonstrations(q, tasks, states, actions, model: ActionModel):
    """The NumPy code the compiled pass replaced (the committed simulation results' code)."""
    rows = q[tasks, states]
    mean = rows.mean(axis=1, keepdims=True)
    centred = rows - mean
    sd = np.sqrt((centred**2).mean(axis=1, keepdims=True) + model.variance_floor)
    sd[sd == 0.0] = 1.0  # the authors' rule for a flat row (no floor)
    relative = rows - rows[:, :1]
    logits = model.beta * relative / sd if model.normalized else model.beta * rows
    shifted = logits - logits.max(axis=1, keepdims=True)
    log_normaliser = libm_log(libm_exp(shifted).sum(axis=1))
    value = float((shifted[np.arange(len(actions)), actions] - log_normaliser).sum())
    g_logits = -libm_exp(shifted - log_normaliser[:, None])
    g_logits[np.arange(len(actions)), actions] += 1.0
    if model.normalized:
        weighted = (g_logits * relative).sum(axis=1, keepdims=True)
        g_rows = model.beta * g_logits / sd - model.beta * weighted * centred / (
            5 * libm_pow(sd, 3.0)
        )
    else:
        g_rows = model.beta * g_logits
    d_q = np.zeros_like(q)
    np.add.at(d_q, (tasks, states), g_rows)
    return value, d_q


def numpy_feedback(q, tasks, states, actions, feedback, model: FeedbackModel):
    rows = q[tasks, states]
    advantage = rows[np.arange(len(actions)), actions] - rows.mean(axis=1)
    sig = 0.5 * (1.0 + np.tanh(0.5 * (model.alpha * advantage)))
    scale = 1.0 - 2.0 * model.epsilon
    positive = (1.0 - model.mu_plus) * (scale * sig + model.epsilon)
    negative = (1.0 - model.mu_minus) * (scale * (1.0 - sig) + model.epsilon)
    slope = (1.0 - 2.0 * model.epsilon) * model.alpha * sig * (1.0 - sig)
    d_positive, d_negative = (1.0 - model.mu_plus) * slope, -(1.0 - model.mu_minus) * slope
    probability = np.where(
        feedback > 0, positive, np.where(feedback < 0, negative, 1.0 - positive - negative)
    )
    d_probability = np.where(
        feedback > 0, d_positive, np.where(feedback < 0, d_negative, -(d_positive + d_negative))
    )
    g_advantage = d_probability / probability
    g_rows = np.repeat((-g_advantage / 5)[:, None], 5, axis=1)
    g_rows[np.arange(len(actions)), actions] += g_advantage
    d_q = np.zeros_like(q)
    np.add.at(d_q, (tasks, states), g_rows)
    return float(libm_log(probability).sum()), d_q


@pytest.mark.parametrize("normalized", [False, True])
def test_the_compiled_pass_gives_the_numpy_code_s_results_to_the_last_bit(
    normalized: bool,
) -> None:
    """The simulations committed in docs/reproduction were made with NumPy code; the compiled
    pass must reproduce it exactly, not approximately: a difference in the last bit of one
    gradient moves whole curves of the feedback experiment (agents act greedily on near-ties)."""
    rng = np.random.default_rng(11)
    q, demo, steps = random_data(rng, 3, 40, 300, 300, scale=15.0)
    for actions, feedback in (
        (ActionModel(1.3, normalized), FeedbackModel()),
        (ActionModel(1.3, normalized, 1e-8), FeedbackModel(epsilon=0.1, alpha=0.7, mu_plus=0.2)),
    ):
        value, d_q = data_log_likelihood(q, *demo, actions, *steps, feedback)
        value_d, d_q_d = numpy_demonstrations(q, *demo, actions)
        value_f, d_q_f = numpy_feedback(q, *steps, feedback)
        assert value == value_d + value_f
        np.testing.assert_array_equal(d_q, d_q_d + d_q_f)
        advantage = rng.normal(size=50) * 3.0
        sig = 0.5 * (1.0 + np.tanh(0.5 * (feedback.alpha * advantage)))
        positive, negative = feedback.probabilities(advantage)
        scale = 1.0 - 2.0 * feedback.epsilon
        np.testing.assert_array_equal(
            positive, (1.0 - feedback.mu_plus) * (scale * sig + feedback.epsilon)
        )
        np.testing.assert_array_equal(
            negative, (1.0 - feedback.mu_minus) * (scale * (1.0 - sig) + feedback.epsilon)
        )


def test_the_kernels_front_page_names_every_error_code_with_its_number() -> None:
    """``_kernels``' docstring says what each compiled error code means: every code of the one
    block here, by name and number, and none that is not in it."""
    import re

    from server.learners import _kernels, likelihoods

    documented = {
        name: int(number)
        for name, number in re.findall(r"``([A-Z_]+)`` \((\d+)\):", _kernels.__doc__ or "")
    }
    codes = {
        name: value
        for name, value in vars(likelihoods).items()
        if name.isupper() and type(value) is int
    }
    assert documented == codes and len(codes) == 7
