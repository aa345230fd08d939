"""Shared core of the grid-world domains: the environment (``Environment``), over the actions,
tasks and sparse transition tables (``tables``) and the learner's parametric transition model
T_theta (``model``), whose names are imported from here as well.

Every environment of the paper has at most a handful of possible successors for each
(state, action) pair, so transitions are stored sparsely: ``next_states[s, a, m]`` with
``probabilities[s, a, m]``. The parametric model is linear in a small vector of "primitive"
probabilities p(theta) (a sigmoid per navigation cell, a softmax row per gravity colour or
farming machine):

    T_theta(s, a, next_states[s, a, m]) = const[s, a, m] + coef[s, a, m] * p(theta)[index[s, a, m]]

which gives the log-likelihood of observed transitions and the pull-back of any gradient on T
to theta with the same few lines for every domain.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from server.domains.model import (
    GRADIENT_RULES,
    LEAST_PROBABILITY,
    RESTRICTIONS_KEPT,
    MovedEntries,
    ObservedTransitions,
    SigmoidModel,
    SoftmaxRowsModel,
    TransitionModel,
    check_gradient_rule,
)
from server.domains.tables import (
    ACTIONS,
    DELTAS,
    DOWN,
    LEFT,
    NUM_ACTIONS,
    RIGHT,
    STAY,
    UP,
    SparseTransitions,
    Task,
    all_finite,
    check_finite,
    check_shape,
    state_numbers,
)

__all__ = [
    "ACTIONS",
    "DELTAS",
    "DOWN",
    "GRADIENT_RULES",
    "LEAST_PROBABILITY",
    "LEFT",
    "NUM_ACTIONS",
    "RESTRICTIONS_KEPT",
    "RIGHT",
    "STAY",
    "UP",
    "Environment",
    "MovedEntries",
    "ObservedTransitions",
    "SigmoidModel",
    "SoftmaxRowsModel",
    "SparseTransitions",
    "Task",
    "TransitionModel",
    "all_finite",
    "check_finite",
    "check_gradient_rule",
    "check_shape",
    "state_numbers",
]


@dataclass
class Environment:
    """A grid-world environment: true dynamics, tasks and the learner's model space.

    States index (cell, feature) pairs: ``state = cell * num_features + feature`` where
    ``cell = row * width + column`` and the feature is the gravity or the machine carried
    (navigation has a single feature).
    """

    name: str
    domain: str
    height: int
    width: int
    num_features: int
    horizon: int
    tasks: tuple[Task, ...]
    true_transitions: SparseTransitions
    model: TransitionModel
    layout: dict[str, Any]  # JSON-serialisable description for drawing (see describe())
    feature_names: tuple[str, ...] = ("none",)
    num_actions: int = NUM_ACTIONS
    # The cells whose cost the learners fit (the authors' learners: in farming only the
    # fields, never the dirt); left empty: every cell.
    cost_cells: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    # How the map draws the environment and the domain's rule, for drawings and checks (not
    # sent to the page): ``letters`` {map letter: wall, floor, terrain, colour or machine},
    # ``palette`` {name: "#rrggbb"} for names the page's palette lacks, and in farming
    # ``works_on`` {machine: terrain}.
    legend: dict[str, Any] = field(default_factory=dict)
    state_cells: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.state_cells = np.arange(self.num_states) // self.num_features
        if self.cost_cells.size == 0:
            self.cost_cells = np.ones(self.num_cells, dtype=bool)
        self.cost_cells = np.asarray(self.cost_cells, dtype=bool)
        if self.cost_cells.shape != (self.num_cells,):
            raise ValueError(f"cost_cells must have one entry per cell ({self.num_cells})")

    # -- sizes ----------------------------------------------------------------------------
    @property
    def num_cells(self) -> int:
        return self.height * self.width

    @property
    def num_states(self) -> int:
        return self.num_cells * self.num_features

    @property
    def task_names(self) -> tuple[str, ...]:
        return tuple(task.name for task in self.tasks)

    # -- states ---------------------------------------------------------------------------
    def state_of(self, row: int, column: int, feature: int = 0) -> int:
        if not (0 <= row < self.height and 0 <= column < self.width):
            raise ValueError(
                f"cell ({row}, {column}) is outside the grid of {self.width} x {self.height} "
                "cells (width x height)"
            )
        if not 0 <= feature < self.num_features:
            raise ValueError(f"feature {feature} out of range 0..{self.num_features - 1}")
        return (row * self.width + column) * self.num_features + feature

    def cell_of(self, state: int) -> tuple[int, int]:
        state = self.check_state(state)
        return divmod(state // self.num_features, self.width)

    def feature_of(self, state: int) -> int:
        return self.check_state(state) % self.num_features

    def check_state(self, state: int) -> int:
        if isinstance(state, bool) or not isinstance(state, int | np.integer):
            raise ValueError(f"state must be an integer, got {state!r}")
        if not 0 <= int(state) < self.num_states:
            raise ValueError(f"state {state} out of range 0..{self.num_states - 1}")
        return int(state)

    def check_action(self, action: int) -> int:
        if isinstance(action, bool) or not isinstance(action, int | np.integer):
            raise ValueError(f"action must be an integer, got {action!r}")
        if not 0 <= int(action) < self.num_actions:
            raise ValueError(
                f"action {action} out of range 0..{self.num_actions - 1} ({', '.join(ACTIONS)})"
            )
        return int(action)

    def check_task(self, task: int) -> int:
        if isinstance(task, bool) or not isinstance(task, int | np.integer):
            raise ValueError(f"task must be an integer, got {task!r}")
        if not 0 <= int(task) < len(self.tasks):
            raise ValueError(f"task {task} out of range 0..{len(self.tasks) - 1}")
        return int(task)

    # -- dynamics -------------------------------------------------------------------------
    def transition_probabilities(self) -> np.ndarray:
        """The true dynamics as a dense (states, actions, states) array whose rows sum to 1."""
        return self.true_transitions.dense()

    def step(self, state: int, action: int, rng: np.random.Generator) -> int:
        state = self.check_state(state)
        action = self.check_action(action)
        probabilities = self.true_transitions.probabilities[state, action]
        successors = self.true_transitions.next_states[state, action]
        if probabilities.max() >= 1.0:
            return int(successors[int(np.argmax(probabilities))])
        return int(rng.choice(successors, p=probabilities / probabilities.sum()))

    def sample_start(self, task: int, rng: np.random.Generator, study: bool = False) -> int:
        task_obj = self.tasks[self.check_task(task)]
        start = task_obj.study_start_distribution if study else task_obj.start
        return int(rng.choice(self.num_states, p=start))

    def is_goal(self, task: int, state: int) -> bool:
        return bool(self.tasks[self.check_task(task)].reward[self.check_state(state)] > 0)

    # -- drawing --------------------------------------------------------------------------
    def describe(self) -> dict[str, Any]:
        """Static JSON-serialisable description for drawing the grid."""
        return {
            "name": self.name,
            "domain": self.domain,
            "height": self.height,
            "width": self.width,
            "horizon": self.horizon,
            "actions": list(ACTIONS),
            "features": list(self.feature_names),
            "tasks": [
                {"name": task.name, "goal_cells": [list(cell) for cell in task.goal_cells]}
                for task in self.tasks
            ],
            **self.layout,
        }

    def describe_state(self, state: int) -> dict[str, Any]:
        """The agent's cell and its feature (the machine carried or the gravity)."""
        row, column = self.cell_of(state)
        feature = self.feature_of(state)
        described: dict[str, Any] = {"state": int(state), "row": row, "column": column}
        if self.domain == "farming":
            described["carrying"] = self.feature_names[feature]
        elif self.domain == "gravity":
            described["gravity"] = self.feature_names[feature]
        return described
