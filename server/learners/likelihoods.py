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

from dataclasses import dataclass

import numpy as np

from server.domains.base import check_finite

# Floor on the per-state variance of Q in the normalised action model: where every action has
# the same value the model is uniform instead of dividing by zero.
VARIANCE_FLOOR = 1e-8


@dataclass(frozen=True)
class ActionModel:
    beta: float = 1.0
    normalized: bool = True

    def __post_init__(self) -> None:
        if not np.isfinite(self.beta) or self.beta <= 0:
            raise ValueError(f"beta must be a positive finite number, got {self.beta!r}")


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
        sig = _sigmoid(self.alpha * advantage)
        scale = 1.0 - 2.0 * self.epsilon
        positive = (1.0 - self.mu_plus) * (scale * sig + self.epsilon)
        negative = (1.0 - self.mu_minus) * (scale * (1.0 - sig) + self.epsilon)
        return positive, negative


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * x))


def _integer_array(name: str, values: np.ndarray) -> np.ndarray:
    """Whole-number indices as int64; fractional or non-finite values are an error, not
    silently truncated."""
    array = np.asarray(values)
    if array.dtype.kind in "iu":
        return array.astype(np.int64).reshape(-1)
    if array.size and array.dtype.kind != "f":
        raise ValueError(f"{name} must be integers, got dtype {array.dtype}")
    if array.size and (not np.all(np.isfinite(array)) or np.any(array != np.round(array))):
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
    d_q = np.zeros_like(q)
    if len(tasks) == 0:
        return 0.0, d_q
    rows = q[tasks, states]  # (N, A)
    if model.normalized:
        mean = rows.mean(axis=1, keepdims=True)
        centred = rows - mean
        sd = np.sqrt((centred**2).mean(axis=1, keepdims=True) + VARIANCE_FLOOR)
        relative = rows - rows[:, :1]  # Q(s, a) - Q(s, STAY)
        logits = model.beta * relative / sd
    else:
        logits = model.beta * rows
    shifted = logits - logits.max(axis=1, keepdims=True)
    log_normaliser = np.log(np.exp(shifted).sum(axis=1))
    chosen = shifted[np.arange(len(actions)), actions]
    value = float((chosen - log_normaliser).sum())
    g_logits = -np.exp(shifted - log_normaliser[:, None])
    g_logits[np.arange(len(actions)), actions] += 1.0
    if model.normalized:
        # logits_b = beta (Q_b - Q_0) / sd; the Q_0 term drops out because sum_b g_b = 0.
        num_actions = rows.shape[1]
        weighted = (g_logits * relative).sum(axis=1, keepdims=True)
        g_rows = model.beta * g_logits / sd - model.beta * weighted * centred / (
            num_actions * sd**3
        )
    else:
        g_rows = model.beta * g_logits
    np.add.at(d_q, (tasks, states), g_rows)
    return value, d_q


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
    if np.any((feedback < -1) | (feedback > 1)):
        raise ValueError("feedback must be +1, -1 or 0 (none)")
    d_q = np.zeros_like(q)
    if len(tasks) == 0:
        return 0.0, d_q
    rows = q[tasks, states]
    advantage = rows[np.arange(len(actions)), actions] - rows.mean(axis=1)
    positive, negative = model.probabilities(advantage)
    sig = _sigmoid(model.alpha * advantage)
    slope = (1.0 - 2.0 * model.epsilon) * model.alpha * sig * (1.0 - sig)
    d_positive = (1.0 - model.mu_plus) * slope
    d_negative = -(1.0 - model.mu_minus) * slope
    probability = np.where(
        feedback > 0, positive, np.where(feedback < 0, negative, 1.0 - positive - negative)
    )
    if np.any(probability <= 0.0):
        raise ValueError(
            "a feedback event has probability 0 under the feedback model "
            "(no feedback is impossible when mu_plus = mu_minus = 0)"
        )
    d_probability = np.where(
        feedback > 0, d_positive, np.where(feedback < 0, d_negative, -(d_positive + d_negative))
    )
    value = float(np.log(probability).sum())
    g_advantage = d_probability / probability
    num_actions = rows.shape[1]
    g_rows = np.repeat((-g_advantage / num_actions)[:, None], num_actions, axis=1)
    g_rows[np.arange(len(actions)), actions] += g_advantage
    np.add.at(d_q, (tasks, states), g_rows)
    return value, d_q


def gaussian_log_prior(
    parameters: np.ndarray, mean: float | np.ndarray, sd: float
) -> tuple[float, np.ndarray]:
    """ln N(parameters; mean, sd^2) summed (without the constant), and its gradient."""
    parameters = check_finite("parameters", parameters)
    if not np.isfinite(sd) or sd <= 0:
        raise ValueError(f"prior standard deviation must be positive, got {sd!r}")
    deviation = parameters - mean
    return float(-0.5 * (deviation**2).sum() / sd**2), -deviation / sd**2
