"""Behavioural cloning (section 4.1): a table Q(s, a) per task fitted to the demonstrated
actions and the feedback under the same action and feedback models as the other learners,
with no generalisation between states; in states without data for a task it acts at random.

As in the paper authors' implementation, each task's table has an optimiser of its own (its
step clipped on its own), the table is clipped to +-3 prior deviations after every step, and
only actions of exactly the best value count as tied."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from numba import njit

from server.domains.base import Environment, check_finite
from server.learners._kernels import clipped_momentum_step
from server.learners.base import Learner
from server.learners.likelihoods import (
    GRADIENT_NOT_FINITE,
    VARIANCE_FLOOR,
    data_log_likelihood_kernel,
    gaussian_log_prior,
    refuse,
    step_advantages,
)
from server.learners.objective import (
    MomentumAscent,
    TeacherData,
    action_model,
    feedback_model,
    likelihood_arguments,
    teacher_log_likelihood,
)
from server.learners.settings import (
    OPTIMIZER_SCOPES,
    CommonSettings,
    check_positive_or_none,
    setting,
    setting_of,
)


def _check_tie_tolerance(name: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0 <= value < 1:
        raise ValueError(f"{name} must be in [0, 1), got {value!r}")


@dataclass(frozen=True, kw_only=True)
class CloningSettings(CommonSettings):
    """Behavioural cloning's settings: its table's prior, clip and optimisers, and its ties."""

    variance_floor: float = setting_of(
        CommonSettings,
        "variance_floor",
        VARIANCE_FLOOR,
        "A floor on a Q row's variance in the normalised action model. The authors' model has "
        "none, but their rows are kept from shrinking to nothing under the prior only by their "
        "gradient's rounding noise (which ours, centring each row, does not make); with no "
        "floor the agent collapses from round 3 (doorway: 6% of the optimum after three "
        "rounds against 70% with the floor; docs/fidelity.md).",
    )
    steps: int = setting(200, "Momentum steps on the table in an update.")
    learning_rate: float = setting(0.01, "The learning rate of the momentum steps.")
    q_prior_sd: float = setting(
        1.0, "The deviation of the table's Gaussian prior N(0, sd), centred on 0."
    )
    q_bound_sds: float | None = setting(
        3.0,
        "The table is clipped to +-this many prior deviations after every step (the "
        "authors': 3); unset: not clipped.",
        check=check_positive_or_none,
    )
    optimizers: str = setting(
        "per-task",
        '"per-task": one optimiser per task\'s table (the authors\'); "joint": one for all.',
        choices=OPTIMIZER_SCOPES,
    )
    tie_tolerance: float = setting(
        0.0,
        "Q values this close (relative) to a state's best count as tied for best, in [0, 1) "
        "(the authors: 0, exact ties only).",
        check=_check_tie_tolerance,
    )
    compiled_steps: bool = setting(
        True,
        "true: an update's momentum steps in one compiled call, 3-4 times faster, the agents "
        'as the NumPy steps\' (docs/defaults.md, "Compiled cloning steps"), not to the last '
        "bit (a step's norm is summed in another order); false: step by step in NumPy, as the "
        "published reproduction runs were made.",
    )


class BehavioralCloning(Learner):
    """Behavioural cloning, ``learners.make("cloning", env)`` (the module docstring)."""

    name = "cloning"
    settings_type: ClassVar[type[CloningSettings]] = CloningSettings
    settings: CloningSettings

    def __init__(self, env: Environment, seed: int = 0, **settings: Any) -> None:
        super().__init__(env, seed, **settings)
        self.table = np.zeros((len(env.tasks), env.num_states, env.num_actions))
        self.optimizer = MomentumAscent(
            self.table.size,
            self.settings.learning_rate,
            self.settings.momentum,
            self.settings.max_step,
            clip=self.settings.momentum_clip,
            rows=len(env.tasks) if self.settings.optimizers == "per-task" else 1,
        )

    def _fit(self) -> tuple[float, int]:
        data = TeacherData.from_log(self.data)
        if data.empty:
            return 0.0, 0
        if self.settings.compiled_steps:
            return self._compiled_steps(data)
        actions, feedback = action_model(self.settings), feedback_model(self.settings)
        sds = self.settings.q_bound_sds
        bound = None if sds is None else float(sds) * float(self.settings.q_prior_sd)
        objective = 0.0
        for _ in range(int(self.settings.steps)):
            value, d_q = teacher_log_likelihood(self.table[data.tasks], data, actions, feedback)
            prior, prior_grad = gaussian_log_prior(self.table, 0.0, self.settings.q_prior_sd)
            grad = prior_grad
            grad[data.tasks] += d_q
            objective = value + prior
            self.table = self.optimizer.step(self.table.ravel(), grad.ravel()).reshape(
                self.table.shape
            )
            if bound is not None:
                self.table = np.clip(self.table, -bound, bound)
        return objective, int(self.settings.steps)

    def _compiled_steps(self, data: TeacherData) -> tuple[float, int]:
        """The steps of ``_fit``, all in one compiled call (``_ascend``): a step is a few
        microseconds of arithmetic, which a NumPy call per operation made 150."""
        steps = int(self.settings.steps)
        if steps <= 0:
            return 0.0, 0
        prior_sd = float(self.settings.q_prior_sd)
        check_finite("Q table", self.table)
        if not np.isfinite(prior_sd) or prior_sd <= 0:
            raise ValueError(f"prior standard deviation must be positive, got {prior_sd!r}")
        table, velocity, before, demo_values, step_values, code = _ascend(
            *self.ascent_arguments(data, steps)
        )
        if code == GRADIENT_NOT_FINITE:
            raise FloatingPointError("the objective's gradient is not finite")
        refuse(code, (len(data.tasks), *self.table.shape[1:]))
        self.table, self.optimizer.velocity = table, velocity
        # The objective at the last step's start, summed as NumPy sums.
        prior = float(-0.5 * (before**2).sum() / prior_sd**2)
        return float(demo_values.sum()) + float(step_values.sum()) + prior, steps

    def ascent_arguments(self, data: TeacherData, steps: int) -> tuple[Any, ...]:
        """``_ascend``'s arguments for ``steps`` steps of this learner's table and optimiser on
        ``data``, as its settings have them."""
        prior_sd = float(self.settings.q_prior_sd)
        sds = self.settings.q_bound_sds
        optimizer = self.optimizer
        return (
            np.ascontiguousarray(self.table, dtype=np.float64),
            np.ascontiguousarray(optimizer.velocity, dtype=np.float64),
            data.tasks.astype(np.int64),
            *likelihood_arguments(data, self.settings),
            steps,
            prior_sd**2,
            optimizer.learning_rate,
            optimizer.momentum,
            optimizer.max_step,
            optimizer.clip == "step",
            optimizer.rows,
            np.inf if sds is None else float(sds) * prior_sd,
        )

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
        tolerance = float(self.settings.tie_tolerance)
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


@njit(cache=True, fastmath=False, error_model="numpy")
def _ascend(
    table,
    velocity,
    tasks,
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
    epsilon,
    alpha,
    mu_plus,
    mu_minus,
    steps,
    prior_variance,
    learning_rate,
    momentum,
    max_step,
    clip_step,
    rows,
    bound,
):  # type: ignore[no-untyped-def]
    """``steps`` momentum steps of the tables (tasks, S, A) on the teacher data's
    log-likelihood (of the tables of ``tasks``, the tasks with data) plus a N(0,
    prior_variance) prior, each step's norm clipped to ``max_step`` per row of ``rows`` (one
    per task, or one for all), the tables clipped to +-``bound``: what
    ``MomentumAscent.step`` and ``data_log_likelihood`` do, element by element in the same
    order (a norm is summed in order, as NumPy may not). Returns the new tables and velocity,
    the tables and the data's per-record log-likelihoods at the last step's start, and an
    error code (0: none)."""
    num_tasks, num_states, num_actions = table.shape
    size = num_states * num_actions
    per_row = table.size // rows
    table = table.copy()
    velocity = velocity.copy()
    flat = table.reshape(table.size)
    q = np.empty((tasks.shape[0], num_states, num_actions))
    grad = np.empty(table.size)
    before = table.copy()
    demo_values = np.zeros(0)
    step_values = np.zeros(0)
    data_row = np.full(num_tasks, -1, dtype=np.int64)  # a task's row in q (-1: no data)
    for t in range(tasks.shape[0]):
        data_row[tasks[t]] = t
    for step in range(steps):
        for t in range(tasks.shape[0]):
            q[t] = table[tasks[t]]
        if step_tasks.shape[0]:
            advantages, code = step_advantages(
                q, step_tasks, step_states, step_actions, step_feedback
            )
            if code:
                return table, velocity, before, demo_values, step_values, code
            sigmoids = 0.5 * (1.0 + np.tanh(0.5 * (alpha * advantages)))  # as _sigmoid
        else:
            sigmoids = np.empty(0)
        demo_values, d_q, step_values, d_q_steps, code = data_log_likelihood_kernel(
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
        )
        if code:
            return table, velocity, before, demo_values, step_values, code
        if step == steps - 1:
            before[:] = table
        demos_flat, steps_flat = d_q.reshape(d_q.size), d_q_steps.reshape(d_q_steps.size)
        for k in range(num_tasks):
            origin, t = k * size, data_row[k]
            for i in range(origin, origin + size):
                grad[i] = -(flat[i] - 0.0) / prior_variance
            if t >= 0:
                for i in range(size):
                    grad[origin + i] += demos_flat[t * size + i] + steps_flat[t * size + i]
        for r in range(rows):
            first, last = r * per_row, (r + 1) * per_row
            # A gradient that is not finite makes its row's norm so.
            if not clipped_momentum_step(
                flat[first:last], velocity[first:last], grad[first:last], learning_rate,
                momentum, max_step, clip_step, bound,
            ):  # fmt: skip
                return table, velocity, before, demo_values, step_values, GRADIENT_NOT_FINITE
    return table, velocity, before, demo_values, step_values, 0
