"""Exact evaluation: optimal returns against shortest paths, and the teacher's own policy
scores a normalised return of 1."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from server import domains
from server.domains.base import Environment
from server.learners.base import Learner
from server.learners.evaluation import (
    normalized_return,
    optimal_returns,
    task_returns,
    total_return,
)
from server.teacher import Teacher
from tests.learners._support import goal_distances


class TeacherPolicy(Learner):
    """A 'learner' that acts greedily on the teacher's hard-max Q."""

    name = "teacher-policy"

    def __init__(self, env: Environment, seed: int = 0, **settings: Any) -> None:
        super().__init__(env, seed, **settings)
        self.teacher = Teacher(env, seed=seed)

    def _fit(self) -> tuple[float, int]:
        return 0.0, 0

    def policy(self, task: int) -> np.ndarray:
        greedy = np.argmax(self.teacher.q_values(task), axis=1)
        return np.eye(self.env.num_actions)[greedy]

    def _parameters_state(self) -> dict[str, np.ndarray]:
        return {}

    def _load_parameters_state(self, state: dict[str, Any]) -> None:
        pass


@pytest.mark.parametrize("name", domains.NAMES)
def test_optimal_returns_from_shortest_paths(name: str) -> None:
    """With deterministic dynamics and reward 1 at the goal, counted on the states reached by
    the H transitions, the best return from s is H - d(s) + 1 for a goal d(s) >= 1 moves away,
    H from the goal itself (0 if unreachable in time)."""
    env = domains.make(name)
    optimal = optimal_returns(env)
    assert optimal.shape == (len(env.tasks),)
    assert np.all(optimal > 0.0) and np.all(optimal <= env.horizon)
    for task in range(len(env.tasks)):
        distance = goal_distances(env, task).astype(float)
        per_state = np.where(
            distance >= 0, np.clip(env.horizon - distance + 1, 0.0, env.horizon), 0.0
        )
        assert optimal[task] == pytest.approx(float(env.tasks[task].start @ per_state), rel=1e-12)


@pytest.mark.parametrize("name", domains.NAMES)
def test_the_teachers_policy_scores_one(name: str) -> None:
    env = domains.make(name)
    learner = TeacherPolicy(env)
    assert normalized_return(env, learner) == pytest.approx(1.0, abs=1e-9)
    assert total_return(env, learner) == pytest.approx(float(optimal_returns(env).sum()), rel=1e-12)
    # The same through task_returns with one action per state.
    greedy = [learner.greedy_policy(task) for task in range(len(env.tasks))]
    np.testing.assert_allclose(task_returns(env, greedy), optimal_returns(env), rtol=1e-12)


def test_a_worse_policy_scores_less() -> None:
    env = domains.make("doorway")
    learner = TeacherPolicy(env)
    policies = [learner.greedy_policy(task) for task in range(len(env.tasks))]
    policies[0] = np.zeros(env.num_states, dtype=np.int64)  # STAY everywhere for task A
    returns = task_returns(env, policies)
    optimal = optimal_returns(env)
    assert returns[0] == pytest.approx(0.0)  # no start state of doorway is a goal
    np.testing.assert_allclose(returns[1:], optimal[1:], rtol=1e-12)


def test_optimal_returns_are_a_copy() -> None:
    env = domains.make("wall")
    optimal_returns(env)[:] = -1.0
    assert np.all(optimal_returns(env) > 0.0)


def test_task_returns_wants_one_policy_per_task() -> None:
    env = domains.make("wall")
    uniform = np.full((env.num_states, env.num_actions), 1.0 / env.num_actions)
    with pytest.raises(ValueError, match="one per task"):
        task_returns(env, [uniform])
    with pytest.raises(ValueError, match="shape"):
        task_returns(env, [uniform[:, :3], uniform])
