"""Behavioural cloning (section 4.1): a table Q(s, a) per task fitted to the demonstrated
actions and the feedback under the same action and feedback models as the other learners,
with no generalisation between states; in states without data for a task it acts at random.

As in the paper authors' implementation, each task's table has an optimiser of its own (its
step clipped on its own), the table is clipped to +-3 prior deviations after every step, and
only actions of exactly the best value count as tied."""

from __future__ import annotations

from typing import Any

import numpy as np

from server.domains.base import Environment, check_finite
from server.learners.base import Learner
from server.learners.likelihoods import VARIANCE_FLOOR, gaussian_log_prior
from server.learners.objective import (
    COMMON_SETTINGS,
    OPTIMIZER_SCOPES,
    MomentumAscent,
    TeacherData,
    action_model,
    check_choice,
    check_positive_or_none,
    feedback_model,
    teacher_log_likelihood,
)


class BehavioralCloning(Learner):
    """Behavioural cloning, ``learners.make("cloning", env)`` (the module docstring)."""

    name = "cloning"
    default_settings = {
        **COMMON_SETTINGS,
        # A floor on a Q row's variance in the normalised action model. The authors' model
        # has none, but their rows are kept from shrinking to nothing under the prior only by
        # their gradient's rounding noise (which ours, centring each row, does not make); with
        # no floor our agent collapses from round 3 (doorway: 6% of the optimum after three
        # rounds against 70% with the floor). Why: docs/reproduction.md, "Fidelity".
        "variance_floor": VARIANCE_FLOOR,
        "steps": 200,
        "learning_rate": 0.01,
        "q_prior_sd": 1.0,
        # The table is clipped to +- this many prior deviations after every step (the
        # authors': 3); None: not clipped.
        "q_bound_sds": 3.0,
        # "per-task": one optimiser per task's table (the authors'); "joint": one for all.
        "optimizers": "per-task",
        # Q values this close (relative) to a state's best count as tied for best (the
        # authors: 0, exact ties only).
        "tie_tolerance": 0.0,
    }

    def __init__(self, env: Environment, seed: int = 0, **settings: Any) -> None:
        super().__init__(env, seed, **settings)
        check_choice("optimizers", self.settings["optimizers"], OPTIMIZER_SCOPES)
        check_positive_or_none("q_bound_sds", self.settings["q_bound_sds"])
        tolerance = self.settings["tie_tolerance"]
        if isinstance(tolerance, bool) or not 0 <= tolerance < 1:
            raise ValueError(f"tie_tolerance must be in [0, 1), got {tolerance!r}")
        self.table = np.zeros((len(env.tasks), env.num_states, env.num_actions))
        self.optimizer = MomentumAscent(
            self.table.size,
            self.settings["learning_rate"],
            self.settings["momentum"],
            self.settings["max_step"],
            clip=self.settings["momentum_clip"],
            rows=len(env.tasks) if self.settings["optimizers"] == "per-task" else 1,
        )

    def _fit(self) -> tuple[float, int]:
        data = TeacherData.from_log(self.data)
        if data.empty:
            return 0.0, 0
        actions, feedback = action_model(self.settings), feedback_model(self.settings)
        sds = self.settings["q_bound_sds"]
        bound = None if sds is None else float(sds) * float(self.settings["q_prior_sd"])
        objective = 0.0
        for _ in range(int(self.settings["steps"])):
            value, d_q = teacher_log_likelihood(self.table[data.tasks], data, actions, feedback)
            prior, prior_grad = gaussian_log_prior(self.table, 0.0, self.settings["q_prior_sd"])
            grad = prior_grad
            grad[data.tasks] += d_q
            objective = value + prior
            self.table = self.optimizer.step(self.table.ravel(), grad.ravel()).reshape(
                self.table.shape
            )
            if bound is not None:
                self.table = np.clip(self.table, -bound, bound)
        return objective, int(self.settings["steps"])

    def policy(self, task: int) -> np.ndarray:
        task = self.env.check_task(task)
        visited = TeacherData.from_log(self.data).visited(len(self.env.tasks), self.env.num_states)[
            task
        ]
        probabilities = np.full(
            (self.env.num_states, self.env.num_actions), 1.0 / self.env.num_actions
        )
        # Where there is data: the table's best action, or an even split between the actions
        # tied for best. Ties are the rule, not an accident: feedback on one action moves the
        # other actions of its state identically, so a state whose only data is "-" on one
        # action has the other actions exactly tied, and picking the first of them would make
        # the agent STAY there for ever.
        rows = self.table[task][visited]
        best = rows.max(axis=1, keepdims=True)
        tolerance = float(self.settings["tie_tolerance"])
        tied = rows >= best - tolerance * np.maximum(1.0, np.abs(best))
        probabilities[visited] = tied / tied.sum(axis=1, keepdims=True)
        return probabilities

    def greedy_policy(self, task: int) -> np.ndarray:
        """An action per state: the table's best action where there is data (one of the tied
        best at random), a random action elsewhere, drawn from the learner's seeded
        generator."""
        probabilities = self.policy(task)
        actions = np.argmax(probabilities, axis=1)
        undecided = probabilities.max(axis=1) < 1.0
        unseen = undecided & (probabilities.min(axis=1) > 0.0)
        actions[unseen] = self.rng.integers(0, self.env.num_actions, size=int(unseen.sum()))
        for state in np.flatnonzero(undecided & ~unseen):
            actions[state] = self.rng.choice(np.flatnonzero(probabilities[state] > 0.0))
        return actions.astype(np.int64)

    def _parameters_state(self) -> dict[str, np.ndarray]:
        return {"table": self.table.copy(), "velocity": self.optimizer.velocity.copy()}

    def _load_parameters_state(self, state: dict[str, Any]) -> None:
        table = check_finite("Q table", state["table"])
        if table.shape != self.table.shape:
            raise ValueError(f"Q table must have shape {self.table.shape}, got {table.shape}")
        self.table = table.copy()
        self.optimizer.velocity = check_finite("velocity", state["velocity"]).copy()
