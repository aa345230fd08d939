"""Log-likelihoods of teacher data given Q-values, each with its gradient dL/dQ.

- Demonstrated actions under the teacher's Boltzmann action model (section 3): the paper's
  plain form p(a|s) proportional to exp(beta Q(s, a)), or the reference settings' normalised
  form p(a|s) proportional to exp(beta (Q(s, a) - Q(s, STAY)) / std_a Q(s, .)), which stays
  meaningful as Q grows with the horizon.
- Feedback under A-SABL (equations (3)-(4)): with advantage delta = Q(s, a) - mean_a Q(s, .),
  p(+) = (1 - mu+)[(1 - 2 eps) sigmoid(alpha delta) + eps],
  p(-) = (1 - mu-)[(1 - 2 eps) sigmoid(-alpha delta) + eps], and no feedback otherwise.
- Gaussian priors on parameters.

Q is an array (tasks, states, actions); data are integer arrays of equal length.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from server.domains.base import all_finite, check_finite

# A floor on the per-state variance of Q in the normalised action model, added before the
# square root, as an alternative to the paper authors' rule (ActionModel.variance_floor = 0:
# no floor, and a row whose values are all equal divides by 1, so the model is uniform there).
VARIANCE_FLOOR = 1e-8

# -- error codes -----------------------------------------------------------------------------
# What a compiled function of the learners returns beside its results: 0, or one of these. The
# one block of them: ``_kernels`` and ``cloning`` import theirs from here (numba compiles them
# in as constants). ``refuse`` raises the likelihood's (1-3); the steps' callers, the others.
BAD_INDEX = 1  # a task, state or action index out of range
BAD_FEEDBACK = 2  # feedback that is not +1, -1 or 0 (none)
IMPOSSIBLE_FEEDBACK = 3  # a feedback event of probability 0 under the feedback model
# 4-8: unused.
GRADIENT_NOT_FINITE = 9  # a step's gradient (cost, theta, dynamics or cloning steps)
LIKELIHOOD_NOT_FINITE = 10  # the teacher data's log-likelihood (Q is not finite)
IMPOSSIBLE_TRANSITION = 11  # an observed transition that no theta of the model space gives
# ``dynamics_steps`` stopped where a step's table has an entry theta moves at zero where the
# passes' layouts have it not (or the reverse): not an error, the caller takes the rest.
LAYOUT_CHANGED = 12


@dataclass(frozen=True)
class ActionModel:
    beta: float = 1.0
    normalized: bool = True
    # Added to the variance of a Q row before its square root; 0 is the authors' rule (a
    # row whose values are all equal divides by 1).
    variance_floor: float = 0.0

    def __post_init__(self) -> None:
        if not np.isfinite(self.beta) or self.beta <= 0:
            raise ValueError(f"beta must be a positive finite number, got {self.beta!r}")
        if not np.isfinite(self.variance_floor) or self.variance_floor < 0:
            raise ValueError(
                f"variance_floor must be a non-negative finite number, got {self.variance_floor!r}"
            )


@dataclass(frozen=True)
class FeedbackModel:
    epsilon: float = 0.05
    alpha: float = 1.0
    mu_plus: float = 0.1
    mu_minus: float = 0.1

    def __post_init__(self) -> None:
        if not 0.0 <= self.epsilon < 0.5:
            raise ValueError(f"epsilon must be in [0, 0.5), got {self.epsilon!r}")
        if not np.isfinite(self.alpha) or self.alpha <= 0:
            raise ValueError(f"alpha must be a positive finite number, got {self.alpha!r}")
        for name in ("mu_plus", "mu_minus"):
            value = getattr(self, name)
            if not 0.0 <= value < 1.0:
                raise ValueError(f"{name} must be in [0, 1), got {value!r}")

    def probabilities(self, advantage: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(p(+), p(-)) for each advantage."""
        sig = _sigmoid(self.alpha * np.asarray(advantage, dtype=np.float64))
        positive, negative = np.empty_like(sig), np.empty_like(sig)
        for i, x in enumerate(sig.flat):
            positive.flat[i], negative.flat[i], _, _ = _asabl(
                x, self.epsilon, self.alpha, self.mu_plus, self.mu_minus
            )
        return positive, negative


def _sigmoid(x: np.ndarray) -> np.ndarray:
    # NumPy's tanh, not the C library's that compiled code calls: they differ in the last
    # bits, and feedback experiments amplify such differences into other agents' curves.
    return 0.5 * (1.0 + np.tanh(0.5 * x))


@njit(cache=True, fastmath=False)
def _asabl(
    sig: float, epsilon: float, alpha: float, mu_plus: float, mu_minus: float
) -> tuple[float, float, float, float]:
    """p(+), p(-) and their derivatives with respect to the advantage (equations (3)-(4)),
    given sig = sigmoid(alpha * advantage)."""
    scale = 1.0 - 2.0 * epsilon
    slope = scale * alpha * sig * (1.0 - sig)
    return (
        (1.0 - mu_plus) * (scale * sig + epsilon),
        (1.0 - mu_minus) * (scale * (1.0 - sig) + epsilon),
        (1.0 - mu_plus) * slope,
        -(1.0 - mu_minus) * slope,
    )


def _integer_array(name: str, values: np.ndarray) -> np.ndarray:
    """Whole-number indices as int64; fractional or non-finite values are an error, not
    silently truncated."""
    array = np.asarray(values)
    if array.dtype.kind in "iu":
        return array.astype(np.int64).reshape(-1)
    if array.size and array.dtype.kind != "f":
        raise ValueError(f"{name} must be integers, got dtype {array.dtype}")
    if array.size and (not all_finite(array) or np.any(array != np.round(array))):
        raise ValueError(f"{name} must be whole numbers")
    return array.astype(np.int64).reshape(-1)


def _check_indices(q: np.ndarray, tasks: np.ndarray, states: np.ndarray, actions: np.ndarray):
    q = check_finite("Q", q)
    if q.ndim != 3:
        raise ValueError(f"Q must have shape (tasks, states, actions), got {q.shape}")
    tasks, states, actions = (
        _integer_array(name, x)
        for name, x in (("tasks", tasks), ("states", states), ("actions", actions))
    )
    if not len(tasks) == len(states) == len(actions):
        raise ValueError("tasks, states and actions must have the same length")
    for name, values, bound in (
        ("task", tasks, q.shape[0]),
        ("state", states, q.shape[1]),
        ("action", actions, q.shape[2]),
    ):
        if len(values) and (values.min() < 0 or values.max() >= bound):
            raise ValueError(f"{name} index out of range 0..{bound - 1}")
    return q, tasks, states, actions


def demonstration_log_likelihood(
    q: np.ndarray,
    tasks: np.ndarray,
    states: np.ndarray,
    actions: np.ndarray,
    model: ActionModel,
) -> tuple[float, np.ndarray]:
    """Sum of ln p(a | s) over demonstrated (task, state, action) rows, and dL/dQ."""
    q, tasks, states, actions = _check_indices(q, tasks, states, actions)
    return data_log_likelihood(q, tasks, states, actions, model, NO_ROWS, NO_ROWS, NO_ROWS, NO_ROWS)


def feedback_log_likelihood(
    q: np.ndarray,
    tasks: np.ndarray,
    states: np.ndarray,
    actions: np.ndarray,
    feedback: np.ndarray,
    model: FeedbackModel,
) -> tuple[float, np.ndarray]:
    """Sum of ln p(f | s, a) under A-SABL over (task, state, action, feedback) rows, feedback in
    {+1, -1, 0 = none}, and dL/dQ."""
    q, tasks, states, actions = _check_indices(q, tasks, states, actions)
    feedback = _integer_array("feedback", feedback)
    if len(feedback) != len(tasks):
        raise ValueError("feedback must have one entry per agent step")
    return data_log_likelihood(
        q, NO_ROWS, NO_ROWS, NO_ROWS, ActionModel(), tasks, states, actions, feedback, model
    )


NO_ROWS = np.empty(0, dtype=np.int64)
NO_SIGMOIDS = np.empty(0)


def data_log_likelihood(
    q: np.ndarray,
    demo_tasks: np.ndarray,
    demo_states: np.ndarray,
    demo_actions: np.ndarray,
    actions: ActionModel,
    step_tasks: np.ndarray,
    step_states: np.ndarray,
    step_actions: np.ndarray,
    step_feedback: np.ndarray,
    feedback: FeedbackModel = FeedbackModel(),
) -> tuple[float, np.ndarray]:
    """Demonstrations' and feedback's log-likelihood together, and dL/dQ, in one compiled
    pass (a learner's update evaluates it hundreds of times). Indices are int64 arrays; out of
    range ones and feedback other than +1, -1, 0 are refused."""
    q = np.ascontiguousarray(q, dtype=np.float64)
    if step_tasks.shape[0]:
        advantages, bad = step_advantages(q, step_tasks, step_states, step_actions, step_feedback)
        refuse(bad, q.shape)
        sigmoids = _sigmoid(float(feedback.alpha) * advantages)
    else:  # demonstrations alone (a demonstrations experiment's every update)
        sigmoids = NO_SIGMOIDS
    demo_values, d_q, step_values, d_q_steps, bad = data_log_likelihood_kernel(
        q,
        demo_tasks,
        demo_states,
        demo_actions,
        float(actions.beta),
        bool(actions.normalized),
        float(actions.variance_floor),
        step_tasks,
        step_states,
        step_actions,
        step_feedback,
        sigmoids,
        float(feedback.epsilon),
        float(feedback.alpha),
        float(feedback.mu_plus),
        float(feedback.mu_minus),
    )
    refuse(bad, q.shape)
    # Summed by NumPy, as before this was compiled: the same value to the last bit.
    value = float(demo_values.sum()) + (float(step_values.sum()) if step_values.shape[0] else 0.0)
    if not math.isfinite(value):
        raise FloatingPointError("the teacher data's log-likelihood is not finite (Q is not)")
    if not step_tasks.shape[0]:
        # d_q_steps is all +0, and d_q holds no -0 (its sums start from +0): d_q + 0 is d_q.
        return value, d_q
    return value, d_q + d_q_steps


def refuse(code: int, shape: tuple[int, ...]) -> None:
    """Raise the error a compiled pass reported (0: none)."""
    if code == BAD_INDEX:
        raise ValueError(f"a task, state or action index is out of range for Q of shape {shape}")
    if code == BAD_FEEDBACK:
        raise ValueError("feedback must be +1, -1 or 0 (none)")
    if code == IMPOSSIBLE_FEEDBACK:
        raise ValueError(
            "a feedback event has probability 0 under the feedback model "
            "(no feedback is impossible when mu_plus = mu_minus = 0)"
        )


@njit(cache=True, fastmath=False)
def step_advantages(q, step_tasks, step_states, step_actions, step_feedback):
    """Q(s, a) - mean_b Q(s, b) of each agent step, and an error code (0: none)."""
    num_tasks, num_states, num_actions = q.shape
    advantages = np.zeros(step_tasks.shape[0])
    for n in range(step_tasks.shape[0]):
        k, s, taken, f = step_tasks[n], step_states[n], step_actions[n], step_feedback[n]
        if not (0 <= k < num_tasks and 0 <= s < num_states and 0 <= taken < num_actions):
            return advantages, BAD_INDEX
        if f < -1 or f > 1:
            return advantages, BAD_FEEDBACK
        row = q[k, s]
        mean = 0.0
        for a in range(num_actions):
            mean += row[a]
        advantages[n] = row[taken] - mean / num_actions
    return advantages, 0


@njit(cache=True, fastmath=False)
def data_log_likelihood_kernel(
    q,
    demo_tasks,
    demo_states,
    demo_actions,
    beta,
    normalized,
    variance_floor,
    step_tasks,
    step_states,
    step_actions,
    step_feedback,
    sigmoids,
    epsilon,
    alpha,
    mu_plus,
    mu_minus,
):
    """Each demonstration's log-likelihood, dL/dQ of the demonstrations, each agent step's,
    dL/dQ of the agent steps, and an error code (0: none). The arithmetic is the module
    docstring's, row by row, in the order of the NumPy code it replaced (identical results to
    the last bit); ``sigmoids`` are sigmoid(alpha * advantage) of the agent steps."""
    num_tasks, num_states, num_actions = q.shape
    d_q = np.zeros_like(q)
    d_q_steps = np.zeros_like(q)
    demo_values = np.zeros(demo_tasks.shape[0])
    step_values = np.zeros(step_tasks.shape[0])
    logits = np.empty(num_actions)
    relative = np.empty(num_actions)
    centred = np.empty(num_actions)
    g = np.empty(num_actions)
    # A demonstration's value and dL/dQ row depend only on (task, state, action), and teachers
    # repeat themselves (doorway, ten rounds: 574 steps, 184 different): each is computed once,
    # at its first step, and every step adds its own copy in step order, as before.
    first_of = np.full(num_tasks * num_states * num_actions, -1, dtype=np.int64)
    rows_d_q = np.empty((demo_tasks.shape[0], num_actions))
    for n in range(demo_tasks.shape[0]):
        k, s, chosen = demo_tasks[n], demo_states[n], demo_actions[n]
        if not (0 <= k < num_tasks and 0 <= s < num_states and 0 <= chosen < num_actions):
            return demo_values, d_q, step_values, d_q_steps, BAD_INDEX
        key = (k * num_states + s) * num_actions + chosen
        seen = first_of[key]
        if seen >= 0:
            demo_values[n] = demo_values[seen]
            for a in range(num_actions):
                d_q[k, s, a] += rows_d_q[seen, a]
            continue
        first_of[key] = n
        row = q[k, s]
        sd = 1.0
        if normalized:
            mean = 0.0
            for a in range(num_actions):
                mean += row[a]
            mean /= num_actions
            variance = 0.0
            for a in range(num_actions):
                centred[a] = row[a] - mean
                variance += centred[a] * centred[a]
            sd = np.sqrt(variance / num_actions + variance_floor)
            if sd == 0.0:  # every action equal, no floor: the authors divide by 1
                sd = 1.0
            for a in range(num_actions):
                relative[a] = row[a] - row[0]  # Q(s, a) - Q(s, STAY)
                logits[a] = beta * relative[a] / sd
        else:
            for a in range(num_actions):
                logits[a] = beta * row[a]
        best = logits[0]
        for a in range(1, num_actions):
            best = max(best, logits[a])
        total = 0.0
        for a in range(num_actions):
            total += np.exp(logits[a] - best)
        log_normaliser = np.log(total)
        demo_values[n] = (logits[chosen] - best) - log_normaliser
        for a in range(num_actions):
            g[a] = -np.exp(logits[a] - best - log_normaliser)
        g[chosen] += 1.0
        if normalized:
            # logits_b = beta (Q_b - Q_0) / sd; the Q_0 term drops out because sum_b g_b = 0.
            weighted = 0.0
            for a in range(num_actions):
                weighted += g[a] * relative[a]
            for a in range(num_actions):
                rows_d_q[n, a] = beta * g[a] / sd - beta * weighted * centred[a] / (
                    num_actions * sd**3.0
                )
        else:
            for a in range(num_actions):
                rows_d_q[n, a] = beta * g[a]
        for a in range(num_actions):
            d_q[k, s, a] += rows_d_q[n, a]
    for n in range(step_tasks.shape[0]):
        k, s, taken, f = step_tasks[n], step_states[n], step_actions[n], step_feedback[n]
        positive, negative, d_positive, d_negative = _asabl(
            sigmoids[n], epsilon, alpha, mu_plus, mu_minus
        )
        if f > 0:
            probability, d_probability = positive, d_positive
        elif f < 0:
            probability, d_probability = negative, d_negative
        else:
            probability, d_probability = 1.0 - positive - negative, -(d_positive + d_negative)
        if probability <= 0.0:
            return demo_values, d_q, step_values, d_q_steps, IMPOSSIBLE_FEEDBACK
        step_values[n] = np.log(probability)
        g_advantage = d_probability / probability
        share = -g_advantage / num_actions
        for a in range(num_actions):
            d_q_steps[k, s, a] += share + g_advantage if a == taken else share
    return demo_values, d_q, step_values, d_q_steps, 0


def gaussian_log_prior(
    parameters: np.ndarray, mean: float | np.ndarray, sd: float
) -> tuple[float, np.ndarray]:
    """ln N(parameters; mean, sd^2) summed (without the constant), and its gradient."""
    parameters = check_finite("parameters", parameters)
    if not np.isfinite(sd) or sd <= 0:
        raise ValueError(f"prior standard deviation must be positive, got {sd!r}")
    deviation = parameters - mean
    return float(-0.5 * (deviation**2).sum() / sd**2), -deviation / sd**2
