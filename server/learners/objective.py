"""Pieces shared by the learners: teacher data as arrays, the optimiser, and the teacher-data
log-likelihood through the soft planner (the first term of the paper's equation (5))."""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from server.domains.base import Environment, TransitionModel, all_finite, state_numbers
from server.learners.base import DataLog
from server.learners.likelihoods import (
    ActionModel,
    FeedbackModel,
    data_log_likelihood,
)
from server.learners.planning import (
    PRECISIONS,
    TransitionOperator,
    check_horizon,
    checked_soft_plan,
)
from server.learners.settings import (
    MOMENTUM_CLIPS,
    CommonSettings,
    PlannerSettings,
    check_choice,
)

# Teacher data is planned over the states it reaches when those are at most this share of
# the states (``TeacherData.restricted``). On an AVX-512 AMD EPYC, 2 cores, 2026-11-28:
# three-fields' data reaches 272 of 384 states, and its passes restricted cost 14-16% less than
# over every state; two-fields' reaches 367, and they cost 1.5-1.8 times as much.
RESTRICT_BELOW = 0.9


def taught_tasks(log: DataLog) -> np.ndarray:
    """The tasks that have demonstrations or agent steps in ``log``, sorted."""
    return np.unique(np.concatenate([log.demonstrations[:, 0], log.agent_steps[:, 0]]))


@dataclass(frozen=True)
class TeacherData:
    """Demonstrated actions and agent steps with feedback, restricted to the tasks that have
    any, re-indexed 0..len(tasks)-1 so the planner only plans the tasks it needs."""

    tasks: np.ndarray  # original task indices with data
    demo_tasks: np.ndarray
    demo_states: np.ndarray
    demo_actions: np.ndarray
    step_tasks: np.ndarray
    step_states: np.ndarray
    step_actions: np.ndarray
    step_feedback: np.ndarray
    # With ``restricted``: the learner's model over the states the data can reach, and those
    # states (the data's states are then their positions in ``plan_states``).
    plan_model: TransitionModel | None = None
    plan_states: np.ndarray | None = None

    @classmethod
    def from_log(cls, log: DataLog, include_silent_steps: bool = True) -> TeacherData:
        demos = log.demonstrations
        steps = log.agent_steps
        if not include_silent_steps:
            steps = steps[steps[:, 4] != 0]
        tasks = np.unique(np.concatenate([demos[:, 0], steps[:, 0]]))
        remap = {int(t): i for i, t in enumerate(tasks)}

        def local(column: np.ndarray) -> np.ndarray:
            return np.array([remap[int(t)] for t in column], dtype=np.int64)

        def column(values: np.ndarray) -> np.ndarray:
            return np.ascontiguousarray(values, dtype=np.int64)

        return cls(
            tasks=tasks,
            demo_tasks=local(demos[:, 0]),
            demo_states=column(demos[:, 1]),
            demo_actions=column(demos[:, 2]),
            step_tasks=local(steps[:, 0]),
            step_states=column(steps[:, 1]),
            step_actions=column(steps[:, 2]),
            step_feedback=column(steps[:, 4]),
        )

    @property
    def empty(self) -> bool:
        return len(self.tasks) == 0

    def restricted(self, model: TransitionModel) -> TeacherData:
        """This data planned over the states it can reach under ``model`` (at any theta):
        the rest have no bearing on its likelihood, and the passes skip them (three-fields:
        112 of 384 states, out of reach of its starts). The likelihood, its gradient and the
        pull-back to theta are the whole model's to the last bit in float64 passes; float32
        passes' gradients to float32's rounding (their reverse pass sums in an order that
        depends on the states planned; tests/learners). The data itself when it has none, or
        reaches more than ``RESTRICT_BELOW`` of the states: renumbering the states breaks the
        grid's fixed offsets between a state and the next (``_kernels.split_rows``), which costs
        more than a few states save (two-fields, 367 of 384 states reached: passes 1.5-1.8
        times as dear restricted)."""
        if self.empty or self.plan_states is not None:
            return self
        states = model.reachable(np.concatenate([self.demo_states, self.step_states]))
        if states.size > RESTRICT_BELOW * model.num_states:
            return self
        number = state_numbers(states, model.num_states)
        return replace(
            self,
            demo_states=number[self.demo_states],
            step_states=number[self.step_states],
            plan_model=model.restricted(states),
            plan_states=states,
        )

    def full_states(self, states: np.ndarray) -> np.ndarray:
        """The environment's state numbers of this data's state numbers."""
        return states if self.plan_states is None else self.plan_states[states]

    def visited(self, num_tasks: int, num_states: int) -> np.ndarray:
        """(tasks, states) mask of the states where the teacher gave data for each task."""
        mask = np.zeros((num_tasks, num_states), dtype=bool)
        mask[self.tasks[self.demo_tasks], self.full_states(self.demo_states)] = True
        mask[self.tasks[self.step_tasks], self.full_states(self.step_states)] = True
        return mask


def action_model(settings: CommonSettings) -> ActionModel:
    return _action_model(
        float(settings.beta), bool(settings.normalized_actions), float(settings.variance_floor)
    )


def feedback_model(settings: CommonSettings) -> FeedbackModel:
    return _feedback_model(
        float(settings.epsilon),
        float(settings.alpha),
        float(settings.mu_plus),
        float(settings.mu_minus),
    )


# The models are immutable and a learner's update asks for them at every step (400 times):
# built, and checked, once per setting.
@functools.lru_cache(maxsize=64)
def _action_model(beta: float, normalized: bool, variance_floor: float) -> ActionModel:
    return ActionModel(beta=beta, normalized=normalized, variance_floor=variance_floor)


@functools.lru_cache(maxsize=64)
def _feedback_model(epsilon: float, alpha: float, mu_plus: float, mu_minus: float) -> FeedbackModel:
    return FeedbackModel(epsilon=epsilon, alpha=alpha, mu_plus=mu_plus, mu_minus=mu_minus)


def likelihood_arguments(data: TeacherData, settings: CommonSettings) -> tuple[Any, ...]:
    """The teacher data and the action and feedback models as the compiled likelihood
    (``likelihoods.data_log_likelihood_kernel``, but for its Q and sigmoids) takes them: the
    demonstrations, the action model, the agent steps, the feedback model."""
    actions, feedback = action_model(settings), feedback_model(settings)
    return (
        data.demo_tasks,
        data.demo_states,
        data.demo_actions,
        float(actions.beta),
        bool(actions.normalized),
        float(actions.variance_floor),
        data.step_tasks,
        data.step_states,
        data.step_actions,
        data.step_feedback,
        float(feedback.epsilon),
        float(feedback.alpha),
        float(feedback.mu_plus),
        float(feedback.mu_minus),
    )


def teacher_log_likelihood(
    q: np.ndarray, data: TeacherData, actions: ActionModel, feedback: FeedbackModel
) -> tuple[float, np.ndarray]:
    """ln p(D_T | Q) over every task with data, and dL/dQ; q is (tasks with data, S, A)."""
    return data_log_likelihood(
        q,
        data.demo_tasks,
        data.demo_states,
        data.demo_actions,
        actions,
        data.step_tasks,
        data.step_states,
        data.step_actions,
        data.step_feedback,
        feedback,
    )


def planned_teacher_log_likelihood(
    operator: TransitionOperator,
    rewards: np.ndarray,
    data: TeacherData,
    settings: PlannerSettings,
    horizon: int,
    need_transitions: bool,
) -> tuple[float, np.ndarray, np.ndarray | None]:
    """Teacher data likelihood with Q from soft value iteration under (operator, rewards).

    ``rewards`` is (tasks with data, S). Returns the value, dL/drewards and, if asked, dL/dT on
    the operator's sparse entries (S, A, M).
    """
    # The rewards come from the learner's costs, finite and bounded (a step refuses a gradient
    # that is not finite; a state's costs are checked as it loads); the likelihood refuses a Q
    # that is not finite, so its dL/dQ is. The action model checks beta.
    actions = action_model(settings)
    plan = checked_soft_plan(
        operator,
        rewards,
        actions.beta,
        check_horizon(horizon),
        dtype=PRECISIONS[settings.planner_precision],
    )
    value, d_q = teacher_log_likelihood(
        plan.q_all.astype(np.float64, copy=False), data, actions, feedback_model(settings)
    )
    d_rewards, d_transitions = plan.checked_backward(d_q, need_transitions=need_transitions)
    return value, d_rewards, d_transitions


class MomentumAscent:
    """Momentum gradient ascent with the norm of the applied step clipped (reference settings:
    momentum 0.7, step norm at most 0.1). Its velocity persists across updates (warm start).

    ``clip``: "step" (the paper authors' rule) keeps the velocity unclipped, velocity =
    momentum x velocity + learning rate x gradient, and clips only the step it applies;
    "velocity" stores the clipped step as the velocity. With ``rows`` > 1 the parameters are
    a (rows, n) matrix whose rows are clipped one by one (the authors fit each task's costs
    with an optimiser of its own)."""

    def __init__(
        self,
        size: int,
        learning_rate: float,
        momentum: float,
        max_step: float,
        clip: str = "step",
        rows: int = 1,
    ) -> None:
        check_choice("momentum_clip", clip, MOMENTUM_CLIPS)
        if rows < 1 or size % rows:
            raise ValueError(f"{size} parameters do not split into {rows} rows")
        self.velocity = np.zeros(size)
        self.learning_rate = float(learning_rate)
        self.momentum = float(momentum)
        self.max_step = float(max_step)
        self.clip = clip
        self.rows = int(rows)

    def step(self, parameters: np.ndarray, gradient: np.ndarray) -> np.ndarray:
        if not all_finite(gradient):
            raise FloatingPointError("the objective's gradient is not finite")
        velocity = self.momentum * self.velocity + self.learning_rate * gradient
        if self.rows == 1:
            norm = float(np.linalg.norm(velocity))
            scale = self.max_step / norm if norm > self.max_step else 1.0
            step = velocity * scale if scale != 1.0 else velocity.copy()
        else:
            matrix = velocity.reshape(self.rows, -1)
            norms = np.sqrt(np.einsum("ij,ij->i", matrix, matrix))
            scales = np.where(norms > self.max_step, self.max_step / np.maximum(norms, 1e-300), 1.0)
            step = (matrix * scales[:, None]).reshape(-1)
        self.velocity = velocity if self.clip == "step" else step
        return parameters + step


def maximize_lbfgs(
    objective: Callable[[np.ndarray], tuple[float, np.ndarray]],
    start: np.ndarray,
    bounds: list[tuple[float | None, float | None]] | None,
    max_evaluations: int,
) -> tuple[np.ndarray, float, int]:
    """Maximise ``objective`` (value, gradient) with L-BFGS-B from ``start``; returns the best
    point, its value and the number of evaluations."""
    from scipy.optimize import minimize

    best: dict[str, Any] = {"value": -np.inf, "x": start.copy()}
    evaluations = 0

    def negative(x: np.ndarray) -> tuple[float, np.ndarray]:
        nonlocal evaluations
        evaluations += 1
        value, gradient = objective(x)
        if not np.isfinite(value) or not all_finite(gradient):
            raise FloatingPointError("the objective or its gradient is not finite")
        if value > best["value"]:
            best["value"], best["x"] = value, x.copy()
        return -value, -gradient

    minimize(
        negative,
        start,
        jac=True,
        method="L-BFGS-B",
        bounds=bounds,
        options={"maxfun": int(max_evaluations), "maxiter": int(max_evaluations)},
    )
    return best["x"], float(best["value"]), evaluations


def cell_rewards(env: Environment, costs: np.ndarray) -> np.ndarray:
    """Per-state rewards (K, S) from per-cell parameters (K, cells), shared across features."""
    return costs[:, env.state_cells]


def cell_gradient(env: Environment, d_rewards: np.ndarray) -> np.ndarray:
    """Pull a gradient on per-state rewards (K, S) back to per-cell parameters (K, cells)."""
    # States are ordered cell-major (state = cell * num_features + feature).
    return d_rewards.reshape(d_rewards.shape[0], env.num_cells, env.num_features).sum(axis=2)
