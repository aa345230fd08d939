"""The cost fit of the planner learners: per-cell costs for every task (the paper's cost
C = -reward), their prior, and their momentum and L-BFGS-B steps on the teacher data's
log-likelihood through the soft planner (the first term of equation (5)) under a given
transition table.

``CellCosts`` implements ``fits.CostFit``, the protocol a planner learner composes
(``PlannerLearner.cost_fit``), for per-cell costs; global cost's ``GlobalCellCosts``
(``global_cost.py``) adds a cost over full states shared by the tasks. A cost fit knows no
dynamics parameters: the table it plans on comes in from the caller, and its teacher gradient
on that table goes back out (``teacher_gradient``) for the dynamics fit to pull back.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from server.domains.base import Environment, check_finite
from server.learners import _kernels, planning
from server.learners._kernels import (
    CostCells,
    CostState,
    CostWorkspace,
    StepSettings,
    TableGradient,
    TaskRecords,
    TeacherModels,
    TeacherPasses,
    Trace,
)
from server.learners.fits import Bounds
from server.learners.likelihoods import (
    GRADIENT_NOT_FINITE,
    LIKELIHOOD_NOT_FINITE,
    gaussian_log_prior,
    refuse,
)
from server.learners.objective import (
    MomentumAscent,
    TeacherData,
    action_model,
    cell_gradient,
    cell_rewards,
    feedback_model,
    likelihood_arguments,
    maximize_lbfgs,
    planned_teacher_log_likelihood,
)
from server.learners.planning import (
    NO_GRADIENT,
    NO_TERMS,
    PRECISIONS,
    TransitionOperator,
    check_horizon,
    task_chunks,
)
from server.learners.settings import CompiledPlannerSteps, PlannerSettings


class CellCosts:
    """Per-cell costs for each of ``env``'s tasks, fitted by momentum steps (each task's in
    one compiled call, or in NumPy) or L-BFGS-B (``fits.CostFit``)."""

    def __init__(self, env: Environment, settings: PlannerSettings) -> None:
        self.env = env
        self.settings = settings
        self.costs = np.zeros((len(env.tasks), env.num_cells))
        # The cells whose costs are fitted (the others stay at 0).
        self.mask = (
            env.cost_cells if settings.cost_cells == "domain" else np.ones(env.num_cells, bool)
        )
        self.optimizer = MomentumAscent(
            self.costs.size,
            settings.cost_learning_rate,
            settings.momentum,
            settings.max_step,
            clip=settings.momentum_clip,
            rows=len(env.tasks) if settings.cost_optimizers == "per-task" else 1,
        )

    # -- rewards, prior and the teacher's likelihood --------------------------------------
    def rewards(self) -> np.ndarray:
        """Per-state rewards (tasks, S) the costs give."""
        return cell_rewards(self.env, self.costs)

    def task_rewards(self, data: TeacherData) -> np.ndarray:
        """Rewards (tasks with data, S) for the planner."""
        return cell_rewards(self.env, self.costs[data.tasks])

    def prior(self, costs: np.ndarray) -> tuple[float, np.ndarray]:
        return gaussian_log_prior(costs, 0.0, self.settings.cost_prior_sd)

    def gradient(self, d_rewards: np.ndarray) -> np.ndarray:
        """dL/d(per-cell costs) of tasks with data from dL/d(per-state rewards): 0 on the cells
        that carry no cost."""
        return cell_gradient(self.env, d_rewards) * self.mask

    def teacher_objective(
        self,
        operator: TransitionOperator,
        data: TeacherData,
        need_transitions: bool,
    ) -> tuple[float, np.ndarray, np.ndarray | None]:
        """Teacher-data log-likelihood, dL/d(per-state rewards of tasks with data), dL/dT
        (on the table of ``operator``)."""
        rewards = self.task_rewards(data)
        if data.plan_states is not None:
            rewards = rewards[:, data.plan_states]
        value, d_rewards, d_transitions = planned_teacher_log_likelihood(
            operator, rewards, data, self.settings, self.env.horizon, need_transitions
        )
        if data.plan_states is not None:
            # States out of the data's reach: 0, as the whole model's reverse pass gives.
            everywhere = np.zeros((d_rewards.shape[0], self.env.num_states))
            everywhere[:, data.plan_states] = d_rewards
            d_rewards = everywhere
        return value, d_rewards, d_transitions

    def teacher_gradient(
        self, operator: TransitionOperator, data: TeacherData, compiled: bool
    ) -> tuple[float, np.ndarray]:
        """``teacher_objective`` with the transition gradient: the teacher data's
        log-likelihood and dL/dT on the table of ``operator``. With ``compiled`` in one
        compiled call (``_kernels.teacher_gradient``, every task in this thread), else by
        ``teacher_objective``'s passes."""
        if not compiled:
            value, _, d_transitions = self.teacher_objective(operator, data, need_transitions=True)
            assert d_transitions is not None
            return value, d_transitions
        passes, d_probs = self.teacher_pass_arguments(operator, data, fresh_rows=False)
        demo_values, step_values, code = _kernels.teacher_gradient(passes)
        value = teacher_value(demo_values, step_values, code, q_shape(operator, data))
        return value, d_probs.astype(np.float64).reshape(
            operator.num_states, operator.num_actions, operator.width
        )

    def teacher_pass_arguments(
        self, operator: TransitionOperator, data: TeacherData, fresh_rows: bool
    ) -> tuple[TeacherPasses, np.ndarray]:
        """``_kernels.teacher_gradient``'s arguments for the costs' rewards on ``operator``
        (with ``fresh_rows``, the passes' probabilities in arrays of their own, for a kernel to
        fill), and the dL/dT it writes."""
        settings = self.settings
        dtype = PRECISIONS[settings.planner_precision]
        horizon = check_horizon(self.env.horizon)
        rewards = self.task_rewards(data)
        if data.plan_states is not None:
            rewards = rewards[:, data.plan_states]
        shape = (rewards.shape[0], operator.num_states, operator.num_actions)
        entries, copies, originals, runs, slots = operator.reverse_entries()
        rows, incoming, scatter = operator.pass_layouts(dtype)
        if fresh_rows:
            rows, incoming = _own_probabilities(rows, dtype), _own_probabilities(incoming, dtype)
        d_probs: np.ndarray = np.zeros(operator.next_flat.shape[0], dtype)
        no_terms = NO_TERMS[dtype]
        gradient = TableGradient(
            operator.next_flat, operator.width, entries, runs, slots, d_probs, no_terms, shape[0],
            no_terms,
        )  # fmt: skip
        passes = TeacherPasses(
            rows,
            incoming,
            scatter,
            np.ascontiguousarray(rewards, dtype),
            dtype(action_model(settings).beta),
            horizon,
            Trace(
                np.empty(shape, dtype),
                np.empty((horizon - 1, shape[0], shape[1]), dtype),
                np.empty((horizon - 1, shape[0], shape[2], shape[1]), dtype),
            ),
            likelihood_arguments(data, settings),
            np.zeros(shape[:2], dtype),
            gradient,
            copies,
            originals,
        )
        return passes, d_probs

    # -- momentum steps ---------------------------------------------------------------------
    def step(self, operator: TransitionOperator, data: TeacherData) -> float:
        """One momentum step on the costs (tasks with data); returns the objective before it."""
        value, d_rewards, _ = self.teacher_objective(operator, data, need_transitions=False)
        grad = np.zeros_like(self.costs)
        grad[data.tasks] = self.gradient(d_rewards)
        prior, prior_grad = self.prior(self.costs)
        bound = self.settings.cost_bound
        updated = self.optimizer.step(self.costs.ravel(), (grad + prior_grad).ravel())
        self.costs = np.clip(updated.reshape(self.costs.shape), -bound, bound)
        return value + prior

    def steps(self, operator: TransitionOperator, data: TeacherData, steps: int) -> float:
        """``steps`` momentum steps on the costs (tasks with data), in one compiled call where
        ``compiled`` (``compiled_steps``), else step by step; returns the objective before the
        last."""
        if steps <= 0:
            return float("nan")
        if self.compiled:
            return self.compiled_steps(operator, data, steps)
        value = float("nan")
        for _ in range(steps):
            value = self.step(operator, data)
        return value

    @property
    def compiled(self) -> bool:
        """Whether ``steps`` run compiled: the setting ``compiled_steps`` (of the learners that
        have it), where each task's costs have an optimiser of their own."""
        settings = self.settings
        return (
            isinstance(settings, CompiledPlannerSteps)
            and bool(settings.compiled_steps)
            and self.optimizer.rows == len(self.env.tasks)
        )

    def compiled_steps(self, operator: TransitionOperator, data: TeacherData, steps: int) -> float:
        """``step`` ``steps`` times, the tasks' steps in one compiled call each
        (``_kernels.cost_steps_tasks``, the tasks split over the planner's threads as a pass's
        are): a step's arithmetic outside its two passes is a few microseconds, which a NumPy
        call per operation made about a hundred (wall: over half of an update)."""
        env = self.env
        num_data = len(data.tasks)
        num_plan = env.num_states if data.plan_states is None else data.plan_states.shape[0]
        prior_sd = float(self.settings.cost_prior_sd)
        if not np.isfinite(prior_sd) or prior_sd <= 0:  # as gaussian_log_prior refuses it
            raise ValueError(f"prior standard deviation must be positive, got {prior_sd!r}")
        costs = np.array(self.costs, dtype=np.float64)  # copies: kept only if every step ends
        velocity = np.array(self.optimizer.velocity, dtype=np.float64).reshape(costs.shape)
        before = np.empty_like(costs)
        demo_values = np.zeros(data.demo_tasks.shape[0])
        step_values = np.zeros(data.step_tasks.shape[0])
        codes = np.zeros(len(env.tasks), dtype=np.int64)
        planning.run_pass(  # by the module, as the passes' are: a benchmark counts them there
            task_chunks(len(env.tasks)),
            _kernels.cost_steps_tasks,
            None,  # on Python threads: one call an update (cost_steps_tasks' docstring)
            self._cost_steps_arguments(
                operator, data, steps, (costs, velocity, before, demo_values, step_values, codes)
            ),
        )
        for code in codes[codes != 0]:
            if code == GRADIENT_NOT_FINITE:
                raise FloatingPointError("the objective's gradient is not finite")
            if code == LIKELIHOOD_NOT_FINITE:
                raise FloatingPointError(
                    "the teacher data's log-likelihood is not finite (Q is not)"
                )
            refuse(int(code), (num_data, num_plan, env.num_actions))
        self.costs, self.optimizer.velocity = costs, velocity.reshape(-1)
        # The objective at the last step's start, summed as the NumPy steps sum it.
        value = float(demo_values.sum()) + (
            float(step_values.sum()) if step_values.shape[0] else 0.0
        )
        prior = float(-0.5 * ((before - 0.0) ** 2).sum() / prior_sd**2)
        return value + prior

    def _cost_steps_arguments(
        self,
        operator: TransitionOperator,
        data: TeacherData,
        steps: int,
        work: tuple[np.ndarray, ...],
    ) -> tuple[Any, ...]:
        """``_kernels.cost_steps_tasks``' arguments for ``steps`` steps on ``data`` planned on
        ``operator``, the costs' and the records' arrays it writes in ``work`` (the costs,
        velocity, costs before the last step, the records' values and the tasks' codes)."""
        env, settings = self.env, self.settings
        costs, velocity, before, demo_values, step_values, codes = work
        dtype = PRECISIONS[settings.planner_precision]
        actions, feedback = action_model(settings), feedback_model(settings)
        horizon = check_horizon(env.horizon)
        optimizer = self.optimizer
        num_data = len(data.tasks)
        plan_states = (
            np.arange(env.num_states, dtype=np.int64)
            if data.plan_states is None
            else data.plan_states.astype(np.int64)
        )
        num_plan = plan_states.shape[0]
        data_row = np.full(len(env.tasks), -1, dtype=np.int64)
        data_row[data.tasks] = np.arange(num_data)
        demo_rows, demo_start = _rows_by_task(data.demo_tasks, num_data)
        step_rows, step_start = _rows_by_task(data.step_tasks, num_data)
        bound = float(settings.cost_bound)
        prior_sd = float(settings.cost_prior_sd)
        cells = CostCells(
            data_row, plan_states, env.state_cells.astype(np.int64), int(env.num_features),
            self.mask.astype(np.float64),
        )  # fmt: skip
        records = TaskRecords(
            demo_rows, demo_start, data.demo_states[demo_rows], data.demo_actions[demo_rows],
            step_rows, step_start, data.step_states[step_rows], data.step_actions[step_rows],
            data.step_feedback[step_rows],
        )  # fmt: skip
        models = TeacherModels(
            float(actions.beta), bool(actions.normalized), float(actions.variance_floor),
            float(feedback.epsilon), float(feedback.alpha), float(feedback.mu_plus),
            float(feedback.mu_minus),
        )  # fmt: skip
        step_settings = StepSettings(
            optimizer.learning_rate, optimizer.momentum, optimizer.max_step,
            optimizer.clip == "step", bound,
        )  # fmt: skip
        trace = Trace(
            np.empty((num_data, num_plan, env.num_actions), dtype),
            np.empty((horizon - 1, num_data, num_plan), dtype),
            np.empty((horizon - 1, num_data, env.num_actions, num_plan), dtype),
        )
        workspace = CostWorkspace(
            np.empty((num_data, num_plan), dtype),
            np.empty((num_data, num_plan), dtype),
            np.empty((num_data, num_plan, env.num_actions), dtype),
        )
        state = CostState(costs, velocity, before, demo_values, step_values, codes)
        return (
            *operator.pass_layouts(dtype), NO_GRADIENT[dtype], dtype(actions.beta), horizon,
            cells, records, models, int(steps), prior_sd**2, step_settings, trace, workspace,
            state,
        )  # fmt: skip

    # -- L-BFGS-B over packed parameter vectors ------------------------------------------
    def vector(self, data: TeacherData) -> np.ndarray:
        """The cost parameters that the teacher data informs, packed into one vector."""
        return self.costs[data.tasks].ravel().copy()

    def set_vector(self, data: TeacherData, vector: np.ndarray) -> None:
        costs = self.costs.copy()
        costs[data.tasks] = vector[: len(data.tasks) * self.env.num_cells].reshape(
            len(data.tasks), self.env.num_cells
        )
        self.costs = costs

    def bounds(self, data: TeacherData) -> Bounds:
        bound = float(self.settings.cost_bound)
        return [(-bound, bound)] * len(self.vector(data))

    def packed_gradient(self, data: TeacherData, d_rewards: np.ndarray) -> tuple[float, np.ndarray]:
        """Cost priors and the gradient of (teacher likelihood + priors) in the packed layout."""
        prior, prior_grad = self.prior(self.costs[data.tasks])
        return prior, (self.gradient(d_rewards) + prior_grad).ravel()

    def fit_lbfgs(
        self, operator: TransitionOperator, data: TeacherData, evaluations: int
    ) -> tuple[float, int]:
        """Costs by L-BFGS-B under a fixed dynamics model; returns (objective, evaluations)."""

        def objective(vector: np.ndarray) -> tuple[float, np.ndarray]:
            self.set_vector(data, vector)
            value, d_rewards, _ = self.teacher_objective(operator, data, need_transitions=False)
            prior, grad = self.packed_gradient(data, d_rewards)
            return value + prior, grad

        best, value, evaluations = maximize_lbfgs(
            objective, self.vector(data), self.bounds(data), evaluations
        )
        self.set_vector(data, best)
        return value, evaluations

    # -- other parameter blocks, momentum and state ---------------------------------------
    def extra_objective(self, d_rewards: np.ndarray) -> tuple[float, dict[str, np.ndarray]]:
        """Objective terms and gradients of parameter blocks besides the costs: none."""
        return 0.0, {}

    def stop_momentum(self) -> None:
        self.optimizer.velocity[:] = 0.0

    def state(self) -> dict[str, np.ndarray]:
        return {"costs": self.costs.copy(), "cost_velocity": self.optimizer.velocity.copy()}

    def load_state(self, state: dict[str, Any]) -> None:
        costs = check_finite("costs", state["costs"])
        if costs.shape != self.costs.shape:
            raise ValueError(f"costs must have shape {self.costs.shape}, got {costs.shape}")
        self.costs = costs.copy()
        self.optimizer.velocity = check_finite("cost velocity", state["cost_velocity"]).copy()


def teacher_value(
    demo_values: np.ndarray, step_values: np.ndarray, code: int, shape: tuple[int, ...]
) -> float:
    """The teacher data's log-likelihood from a compiled gradient's records' values, summed as
    data_log_likelihood sums them; its error raised (``shape``: Q's, for the message)."""
    if code == LIKELIHOOD_NOT_FINITE:
        raise FloatingPointError("the teacher data's log-likelihood is not finite (Q is not)")
    refuse(int(code), shape)
    value = float(demo_values.sum()) + (float(step_values.sum()) if step_values.shape[0] else 0.0)
    if not np.isfinite(value):
        raise FloatingPointError("the teacher data's log-likelihood is not finite (Q is not)")
    return value


def q_shape(operator: TransitionOperator, data: TeacherData) -> tuple[int, ...]:
    """Q's shape for ``data`` planned on ``operator``."""
    return (len(data.tasks), operator.num_states, operator.num_actions)


def _rows_by_task(tasks: np.ndarray, num_tasks: int) -> tuple[np.ndarray, np.ndarray]:
    """The records' places grouped by task, each task's in the data's order, and where each
    task's begin (``num_tasks + 1`` bounds)."""
    rows = np.argsort(tasks, kind="stable").astype(np.int64)
    start = np.searchsorted(tasks[rows], np.arange(num_tasks + 1)).astype(np.int64)
    return rows, start


def _own_probabilities(layout: Any, dtype: type) -> Any:
    """A pass layout whose probabilities (its arrays in the passes' precision) are copies, for
    a kernel to fill; its index arrays shared."""
    return layout._make(a.copy() if a.dtype == dtype else a for a in layout)
