"""Helpers shared by the learning-core tests: central finite differences, shortest paths on
the true dynamics, and simulated teaching rounds."""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

import numpy as np

from server.domains.base import STAY, Environment
from server.learners.base import Learner
from server.teacher import Teacher

H = 1e-6  # central finite-difference step


def central_difference(
    function: Callable[[np.ndarray], float],
    x: np.ndarray,
    indices: np.ndarray | None = None,
    h: float = H,
) -> np.ndarray:
    """(f(x + h e_i) - f(x - h e_i)) / 2h for the flat ``indices`` of x (all if None)."""
    x = np.asarray(x, dtype=np.float64)
    flat_indices = np.arange(x.size) if indices is None else np.asarray(indices)
    result = np.empty(len(flat_indices))
    for n, i in enumerate(flat_indices):
        plus, minus = x.copy(), x.copy()
        plus.flat[i] += h
        minus.flat[i] -= h
        result[n] = (function(plus) - function(minus)) / (2 * h)
    return result


def probe_indices(gradient: np.ndarray, rng: np.random.Generator, count: int = 5) -> np.ndarray:
    """Flat indices to check by finite differences: the ``count`` largest entries of the
    analytic gradient (so a wrong gradient where it matters is caught) and ``count`` random
    ones (so a gradient that should be zero but is not, or the reverse, is caught)."""
    flat = np.abs(np.asarray(gradient)).ravel()
    largest = np.argsort(flat)[::-1][:count]
    random = rng.choice(flat.size, size=min(count, flat.size), replace=False)
    return np.unique(np.concatenate([largest, random]))


def assert_deterministic(env: Environment) -> None:
    probabilities = env.true_transitions.probabilities
    assert np.all((np.isclose(probabilities, 0.0)) | np.isclose(probabilities, 1.0))


def goal_distances(env: Environment, task: int) -> np.ndarray:
    """Fewest moves from every state to a goal state of ``task`` under the true dynamics
    (breadth-first search backwards from the goals; -1 where no goal is reachable)."""
    next_states = env.true_transitions.next_states
    possible = env.true_transitions.probabilities > 0.0
    predecessors: list[set[int]] = [set() for _ in range(env.num_states)]
    for s, _a, m in zip(*np.nonzero(possible), strict=True):
        predecessors[int(next_states[s, _a, m])].add(int(s))
    distance = np.full(env.num_states, -1)
    queue: deque[int] = deque()
    for s in np.flatnonzero(env.tasks[task].reward > 0):
        distance[s] = 0
        queue.append(int(s))
    while queue:
        state = queue.popleft()
        for previous in predecessors[state]:
            if distance[previous] < 0:
                distance[previous] = distance[state] + 1
                queue.append(previous)
    return distance


def demonstrate_round(
    learner: Learner, env: Environment, teacher: Teacher, rng: np.random.Generator
) -> list[tuple[int, int, int, int]]:
    """One round: a demonstration per task from the task's start distribution, recorded in
    the learner. Returns the recorded (task, state, action, next_state) rows."""
    rows = []
    for task in range(len(env.tasks)):
        start = env.sample_start(task, rng)
        for state, action, next_state in teacher.demonstration(task, start):
            learner.record_demonstration(task, state, action, next_state)
            rows.append((task, state, action, next_state))
    return rows


def agent_episode(
    learner: Learner,
    env: Environment,
    teacher: Teacher,
    rng: np.random.Generator,
    task: int,
    steps: int,
) -> None:
    """``steps`` random agent moves for ``task`` with the teacher's feedback, recorded."""
    state = env.sample_start(task, rng)
    for _ in range(steps):
        action = int(rng.integers(env.num_actions))
        next_state = env.step(state, action, rng)
        learner.record_agent_step(
            task, state, action, next_state, teacher.feedback(task, state, action)
        )
        state = next_state


def idle_transitions(
    learner: Learner, env: Environment, rng: np.random.Generator, count: int
) -> None:
    """Moves without a task (the study's idle mode), recorded as transitions alone."""
    state = env.sample_start(0, rng)
    for _ in range(count):
        action = int(rng.integers(1, env.num_actions))
        next_state = env.step(state, action, rng)
        learner.record_idle_move(state, action, next_state)
        state = next_state


def is_failed_move(state: int, action: int, next_state: int) -> bool:
    return action != STAY and next_state == state
