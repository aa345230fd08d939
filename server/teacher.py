"""The simulated teacher: optimal demonstrations from hard-max value iteration on the true
dynamics and feedback sampled from A-SABL on the teacher's Q.

Two styles of demonstration:

- "authors" (the default; the paper authors' simulated teacher): at every step an action drawn
  uniformly from all the optimal actions, STAY included where it ties; at most ``horizon``
  steps, and when a step reaches a goal state, one more optimal action there (any of them: in
  farming often a move within the field), then the demonstration ends.
- "person" (what a study participant can do): moves only, never STAY, until the first goal
  state, then one STAY (the study page appends it), at most ``horizon`` steps in all.

``next_action`` is a person's move (the simulated study participants press arrow keys).
``mistake_probability`` makes the teacher take a uniformly random move instead, to simulate
imperfect people.
"""

from __future__ import annotations

import numpy as np

from server.domains.base import STAY, Environment
from server.learners.likelihoods import FeedbackModel
from server.learners.planning import TransitionOperator, hard_value_iteration

Step = tuple[int, int, int]  # (state, action, next_state)
STYLES = ("authors", "person")

# Actions whose values are within this of the best count as ties.
TIE_TOLERANCE = 1e-9


class Teacher:
    def __init__(
        self,
        env: Environment,
        seed: int = 0,
        epsilon: float = 0.05,
        mu: float = 0.1,
        alpha: float = 1.0,
        mistake_probability: float = 0.0,
        style: str = "authors",
    ) -> None:
        if not 0.0 <= mistake_probability <= 1.0:
            raise ValueError(f"mistake_probability must be in [0, 1], got {mistake_probability!r}")
        if style not in STYLES:
            raise ValueError(f"style must be one of {', '.join(map(repr, STYLES))}, got {style!r}")
        self.style = style
        self.env = env
        self.rng = np.random.default_rng(seed)
        self.feedback_model = FeedbackModel(epsilon=epsilon, alpha=alpha, mu_plus=mu, mu_minus=mu)
        self.mistake_probability = float(mistake_probability)
        rewards = np.stack([task.reward for task in env.tasks])
        self.q = hard_value_iteration(
            TransitionOperator.build(env.true_transitions), rewards, env.horizon
        )

    def q_values(self, task: int) -> np.ndarray:
        return self.q[self.env.check_task(task)]

    def best_actions(self, task: int, state: int) -> np.ndarray:
        row = self.q_values(task)[self.env.check_state(state)]
        return np.flatnonzero(row >= row.max() - TIE_TOLERANCE)

    def _mistake(self) -> int | None:
        """A uniformly random move with ``mistake_probability``, else None."""
        if self.mistake_probability and self.rng.random() < self.mistake_probability:
            return int(self.rng.integers(1, self.env.num_actions))
        return None

    def next_action(self, task: int, state: int) -> int:
        """The teacher's move in ``state`` (never STAY: people cannot press it)."""
        mistake = self._mistake()
        if mistake is not None:
            return mistake
        best = self.best_actions(task, state)
        moves = best[best != STAY]
        return int(self.rng.choice(moves if len(moves) else best))

    def optimal_action(self, task: int, state: int) -> int:
        """One of the optimal actions in ``state``, uniformly, STAY included (the authors')."""
        mistake = self._mistake()
        if mistake is not None:
            return mistake
        return int(self.rng.choice(self.best_actions(task, state)))

    def demonstration(self, task: int, start_state: int) -> list[Step]:
        """A demonstration from ``start_state`` in the teacher's style (module docstring)."""
        task = self.env.check_task(task)
        state = self.env.check_state(start_state)
        steps: list[Step] = []
        if self.style == "authors":
            while len(steps) < self.env.horizon:
                action = self.optimal_action(task, state)
                next_state = self.env.step(state, action, self.rng)
                steps.append((state, action, next_state))
                state = next_state
                if self.env.is_goal(task, state):
                    action = self.optimal_action(task, state)
                    steps.append((state, action, self.env.step(state, action, self.rng)))
                    break
            return steps
        while not self.env.is_goal(task, state) and len(steps) < self.env.horizon - 1:
            action = self.next_action(task, state)
            next_state = self.env.step(state, action, self.rng)
            steps.append((state, action, next_state))
            state = next_state
        steps.append((state, STAY, self.env.step(state, STAY, self.rng)))
        return steps

    def feedback(self, task: int, state: int, action: int) -> int:
        """+1, -1 or 0 (none), sampled from A-SABL on the teacher's Q."""
        row = self.q_values(task)[self.env.check_state(state)]
        advantage = row[self.env.check_action(action)] - row.mean()
        positive, negative = self.feedback_model.probabilities(np.array([advantage]))
        u = self.rng.random()
        if u < positive[0]:
            return 1
        if u < positive[0] + negative[0]:
            return -1
        return 0
