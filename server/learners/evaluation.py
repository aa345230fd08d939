"""Exact evaluation of a learner's policies: expected total return over all tasks under the
true dynamics, relative to the optimal total return (no sampled episodes).

An episode's return counts, as the paper authors' evaluation does, the rewards of the states
reached after each of the horizon's H transitions, r(s_1) ... r(s_H): the optimal totals then
equal their expert's (doorway 129.1 against their 129.2)."""

from __future__ import annotations

import numpy as np

from server.domains.base import Environment
from server.learners.base import Learner
from server.learners.planning import TransitionOperator, expected_return, hard_value_iteration

_cache: dict[int, tuple[Environment, TransitionOperator, np.ndarray]] = {}


def _true_dynamics(env: Environment) -> tuple[TransitionOperator, np.ndarray]:
    """The true transition operator and each task's optimal expected return (cached)."""
    cached = _cache.get(id(env))
    if cached is None or cached[0] is not env:
        operator = TransitionOperator.build(env.true_transitions)
        rewards = np.stack([task.reward for task in env.tasks])
        # H + 1 backups count r(s_0) ... r(s_H); less r(s_0), the optimum of r(s_1) ... r(s_H).
        q = hard_value_iteration(operator, rewards, env.horizon + 1)
        optimal = np.array(
            [
                float(task.start @ (q[k].max(axis=1) - task.reward))
                for k, task in enumerate(env.tasks)
            ]
        )
        cached = (env, operator, optimal)
        _cache[id(env)] = cached
    return cached[1], cached[2]


def optimal_returns(env: Environment) -> np.ndarray:
    """Each task's optimal expected return over the horizon from its start distribution."""
    return _true_dynamics(env)[1].copy()


def task_returns(env: Environment, policies: list[np.ndarray]) -> np.ndarray:
    """Exact expected return of each task's policy ((S, A) probabilities or (S,) actions)."""
    if len(policies) != len(env.tasks):
        raise ValueError(f"expected {len(env.tasks)} policies, one per task, got {len(policies)}")
    operator, _ = _true_dynamics(env)
    return np.array(
        [
            expected_return(
                operator, policy, task.reward, task.start, env.horizon, after_transitions=True
            )
            for policy, task in zip(policies, env.tasks, strict=True)
        ]
    )


def total_return(env: Environment, learner: Learner) -> float:
    return float(task_returns(env, [learner.policy(k) for k in range(len(env.tasks))]).sum())


def normalized_return(env: Environment, learner: Learner) -> float:
    """The learner's exact expected total return over all tasks / the optimal total return."""
    return total_return(env, learner) / float(optimal_returns(env).sum())
