"""The actions, the tasks and the sparse transition tables of the grid-world domains, with the
checks of the arrays they hold.

Transitions are stored sparsely: ``next_states[s, a, m]`` with ``probabilities[s, a, m]``, every
environment of the paper having at most a handful of possible successors for each (state,
action) pair.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ACTIONS: tuple[str, ...] = ("STAY", "UP", "DOWN", "LEFT", "RIGHT")


STAY, UP, DOWN, LEFT, RIGHT = range(5)


NUM_ACTIONS = len(ACTIONS)


# (row, column) offsets, row 0 at the top.
DELTAS: tuple[tuple[int, int], ...] = ((0, 0), (-1, 0), (1, 0), (0, -1), (0, 1))


def state_numbers(states: np.ndarray, num_states: int) -> np.ndarray:
    """For each of ``num_states`` states, its position in ``states`` (sorted), else -1."""
    number = np.full(num_states, -1, dtype=np.int64)
    number[states] = np.arange(len(states))
    return number


def all_finite(array: np.ndarray) -> bool:
    """No NaN or infinity in ``array`` (the array's own ``all``: a learner's update asks
    thousands of times, and ``np.all``'s dispatch took longer than the check)."""
    return bool(np.isfinite(array).all())


def check_finite(name: str, values: np.ndarray) -> np.ndarray:
    """Reject NaN or infinite parameters at the boundary instead of propagating them."""
    array = np.asarray(values, dtype=np.float64)
    if not all_finite(array):
        raise ValueError(f"{name} contains NaN or infinite values")
    return array


def check_shape(name: str, values: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    array = np.asarray(values)
    if array.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {array.shape}")
    return array


@dataclass(frozen=True)
class Task:
    """One task of an environment: reward 1 on its goal cells, 0 elsewhere."""

    name: str
    reward: np.ndarray  # (states,)
    start: np.ndarray  # (states,) distribution used in simulation
    goal_cells: tuple[tuple[int, int], ...]
    study_start: np.ndarray | None = None  # (states,) distribution used in the user study

    @property
    def study_start_distribution(self) -> np.ndarray:
        return self.start if self.study_start is None else self.study_start


@dataclass(frozen=True)
class SparseTransitions:
    """Transition probabilities T(s, a, next_states[s, a, m]) = probabilities[s, a, m]."""

    next_states: np.ndarray  # (S, A, M) int64
    probabilities: np.ndarray  # (S, A, M) float64

    @property
    def num_states(self) -> int:
        return int(self.next_states.shape[0])

    def dense(self) -> np.ndarray:
        s, a, m = self.next_states.shape
        out = np.zeros((s, a, s))
        rows = np.broadcast_to(np.arange(s)[:, None, None], (s, a, m))
        cols = np.broadcast_to(np.arange(a)[None, :, None], (s, a, m))
        np.add.at(out, (rows, cols, self.next_states), self.probabilities)
        return out

    @classmethod
    def from_dense(cls, transitions: np.ndarray) -> SparseTransitions:
        transitions = np.asarray(transitions, dtype=np.float64)
        if transitions.ndim != 3 or transitions.shape[0] != transitions.shape[2]:
            raise ValueError(
                f"transitions must have shape (states, actions, states), got {transitions.shape}"
            )
        s, a, _ = transitions.shape
        width = max(1, int((transitions > 0).sum(axis=2).max()))
        next_states = np.tile(np.arange(s)[:, None, None], (1, a, width))
        probabilities = np.zeros((s, a, width))
        for state in range(s):
            for action in range(a):
                (successors,) = np.nonzero(transitions[state, action])
                next_states[state, action, : len(successors)] = successors
                probabilities[state, action, : len(successors)] = transitions[
                    state, action, successors
                ]
        return cls(next_states.astype(np.int64), probabilities)
