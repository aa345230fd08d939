"""Base of the learners that act on a learned dynamics model and learned per-cell costs through
the soft planner: BAM, model-based IRL and model-based IRL with a global cost."""

from __future__ import annotations

from typing import Any

import numpy as np

from server.domains.base import (
    Environment,
    ObservedTransitions,
    SigmoidModel,
    SoftmaxRowsModel,
    TransitionModel,
    check_finite,
    check_gradient_rule,
)
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
from server.learners.base import Learner
from server.learners.likelihoods import (
    GRADIENT_NOT_FINITE,
    IMPOSSIBLE_TRANSITION,
    LAYOUT_CHANGED,
    LIKELIHOOD_NOT_FINITE,
    gaussian_log_prior,
    refuse,
)
from server.learners.objective import (
    COMMON_SETTINGS,
    COST_SETTINGS,
    OPTIMIZER_SCOPES,
    OPTIMIZERS,
    MomentumAscent,
    TeacherData,
    action_model,
    cell_gradient,
    cell_rewards,
    check_choice,
    check_positive_or_none,
    feedback_model,
    likelihood_arguments,
    maximize_lbfgs,
    planned_teacher_log_likelihood,
    taught_tasks,
)
from server.learners.planning import (
    NO_GRADIENT,
    NO_TERMS,
    PRECISIONS,
    TransitionOperator,
    check_horizon,
    soft_plan,
    task_chunks,
)

THETA_BOUND = 15.0
COST_CELLS = ("domain", "every")


def check_count(name: str, value: Any, minimum: int) -> None:
    """A whole-number setting of at least ``minimum`` (0 or 1); bools are refused."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < minimum:
        kind = "positive" if minimum == 1 else "non-negative"
        raise ValueError(f"{name} must be a {kind} integer, got {value!r}")


def check_share(name: str, value: Any) -> None:
    """A setting that is a number in (0, 1]; bools are refused."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0 < value <= 1:
        raise ValueError(f"{name} must be a number greater than 0 and at most 1, got {value!r}")


class PlannerLearner(Learner):
    """Learned dynamics parameters theta (the environment's model space) and per-cell reward
    parameters per task (the paper's cost C = -reward), acting greedily on soft Q.

    Over 250 lines: the core that BAM and both IRL baselines share (parameters, the fit's
    schedule and optimiser state, saving and restoring them), kept in one class so that a
    learner's state round-trips through one ``state_dict``."""

    default_settings = {**COMMON_SETTINGS, **COST_SETTINGS}
    warm_up_settings = {"cost_steps": 1, "dynamics_steps": 1}

    def __init__(self, env: Environment, seed: int = 0, **settings: Any) -> None:
        super().__init__(env, seed, **settings)
        if self.settings["optimizer"] not in OPTIMIZERS:
            raise ValueError(
                f"optimizer must be one of {', '.join(repr(o) for o in OPTIMIZERS)}, "
                f"got {self.settings['optimizer']!r}"
            )
        for name in ("max_evaluations", "warm_evaluations"):
            check_count(name, self.settings[name], minimum=1)
        check_share("warm_share", self.settings["warm_share"])
        check_choice("cost_optimizers", self.settings["cost_optimizers"], OPTIMIZER_SCOPES)
        check_choice("cost_cells", self.settings["cost_cells"], COST_CELLS)
        check_choice("planner_precision", self.settings["planner_precision"], tuple(PRECISIONS))
        check_gradient_rule(self.settings["dynamics_gradient"])
        check_positive_or_none("dynamics_prior_sd", self.settings["dynamics_prior_sd"])
        self.theta = env.model.initial_parameters()
        self.costs = np.zeros((len(env.tasks), env.num_cells))
        # The cells whose costs are fitted (the others stay at 0).
        self.cost_mask = (
            env.cost_cells
            if self.settings["cost_cells"] == "domain"
            else np.ones(env.num_cells, bool)
        )
        self.theta_optimizer = MomentumAscent(
            env.model.num_parameters,
            self.settings["dynamics_learning_rate"],
            self.settings["momentum"],
            self.settings["max_step"],
            clip=self.settings["momentum_clip"],
        )
        self.cost_optimizer = MomentumAscent(
            self.costs.size,
            self.settings["cost_learning_rate"],
            self.settings["momentum"],
            self.settings["max_step"],
            clip=self.settings["momentum_clip"],
            rows=len(env.tasks) if self.settings["cost_optimizers"] == "per-task" else 1,
        )
        # Tasks whose costs an update has fitted (a task's first fit is a cold start).
        self.fitted_tasks = np.zeros(len(env.tasks), dtype=bool)
        self._policies: np.ndarray | None = None

    # -- the optimiser schedule -------------------------------------------------------------
    def schedule(self, data: TeacherData) -> tuple[str, int]:
        """This update's optimiser, "momentum" or "lbfgs", and its L-BFGS-B evaluation cap."""
        optimizer = self.settings["optimizer"]
        if optimizer == "lbfgs":
            return "lbfgs", int(self.settings["max_evaluations"])
        if optimizer == "warm-lbfgs":
            if self.warm(data):
                return "lbfgs", int(self.settings["warm_evaluations"])
            # A cold start: the momentum schedule from rest.
            self.stop_momentum()
        return "momentum", 0

    def warm(self, data: TeacherData) -> bool:
        """Whether this update starts warm: an earlier update has fitted every task in ``data``."""
        return self.updates > 0 and bool(np.all(self.fitted_tasks[data.tasks]))

    def momentum_steps(self, steps: int, data: TeacherData) -> int:
        """``steps`` of the momentum schedule, or their ``warm_share`` on a warm update: at
        least one, and none where the schedule has none."""
        if not self.warm(data):
            return steps
        return min(steps, max(1, round(steps * float(self.settings["warm_share"]))))

    def stop_momentum(self) -> None:
        """Momentum steps from rest next: the velocity of earlier momentum steps is stale
        after L-BFGS-B has moved the parameters."""
        self.theta_optimizer.velocity[:] = 0.0
        self.cost_optimizer.velocity[:] = 0.0

    # -- the model ------------------------------------------------------------------------
    def rewards(self) -> np.ndarray:
        """Per-state rewards (tasks, S) the learner currently believes in."""
        return cell_rewards(self.env, self.costs)

    def operator(self, data: TeacherData | None = None) -> TransitionOperator:
        """The learned model's table at theta: over the states ``data`` plans on (see
        ``TeacherData.restricted``), or all states."""
        # dL/dT is only ever pulled back to theta, which reads the entries theta moves.
        return TransitionOperator.of_model(self.plan_model(data), self.theta)

    def teacher_data(self) -> TeacherData:
        """The recorded teacher data, planned over the states it can reach."""
        return TeacherData.from_log(self.data).restricted(self.env.model)

    def plan_model(self, data: TeacherData | None) -> TransitionModel:
        if data is None or data.plan_model is None:
            return self.env.model
        return data.plan_model

    def pullback(
        self, data: TeacherData, d_transitions: np.ndarray, exact: bool = True
    ) -> np.ndarray:
        """A gradient on the table of ``operator(data)``, pulled back to theta (with
        ``exact=False``, by the setting's gradient rule)."""
        return self.plan_model(data).pullback(
            self.theta, d_transitions, rule=self.gradient_rule(exact)
        )

    def q_values(self) -> np.ndarray:
        """Soft Q (tasks, S, A) under the learned model and rewards."""
        return soft_plan(
            self.operator(),
            self.rewards(),
            self.settings["beta"],
            self.env.horizon,
            keep_trace=False,
        ).q_all

    def policy(self, task: int) -> np.ndarray:
        task = self.env.check_task(task)
        if self._policies is None:
            greedy = np.argmax(self.q_values(), axis=2)
            policies = np.zeros((len(self.env.tasks), self.env.num_states, self.env.num_actions))
            np.put_along_axis(policies, greedy[:, :, None], 1.0, axis=2)
            self._policies = policies
        return self._policies[task]

    # -- objective pieces -----------------------------------------------------------------
    def cost_prior(self, costs: np.ndarray) -> tuple[float, np.ndarray]:
        return gaussian_log_prior(costs, 0.0, self.settings["cost_prior_sd"])

    def dynamics_prior(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        """ln m(theta): the setting's Gaussian, else the model space's own prior (or none)."""
        sd = self.settings["dynamics_prior_sd"]
        if sd is None:
            sd = self.env.model.prior_sd
        if sd is None:
            return 0.0, np.zeros_like(theta)
        return gaussian_log_prior(theta, self.env.model.initial_value, sd)

    def gradient_rule(self, exact: bool) -> str:
        """The dynamics gradient of a momentum step ("authors" or "exact"); L-BFGS-B needs the
        exact one (``exact``)."""
        return "exact" if exact else str(self.settings["dynamics_gradient"])

    def transition_objective(
        self,
        theta: np.ndarray,
        observed: np.ndarray | ObservedTransitions,
        exact: bool = True,
    ) -> tuple[float, np.ndarray]:
        """ln T_theta over observed transitions plus ln m(theta), and the gradient (with
        ``exact=False``, the setting's gradient rule)."""
        value, grad = self.env.model.transition_log_likelihood(
            theta, observed, rule=self.gradient_rule(exact)
        )
        prior, prior_grad = self.dynamics_prior(theta)
        return value + prior, grad + prior_grad

    def theta_step(self, grad: np.ndarray) -> None:
        """One momentum step on theta, clipped where the model space clips it (the authors)."""
        theta = self.theta_optimizer.step(self.theta, grad)
        bound = self.env.model.parameter_bound
        self.theta = theta if bound is None else np.clip(theta, -bound, bound)

    def teacher_gradient(self, data: TeacherData) -> tuple[float, np.ndarray]:
        """``teacher_objective`` of the table at theta with the transition gradient: the
        teacher data's log-likelihood and dL/dT on the table of ``operator(data)``. In one
        compiled call where ``compiles_theta_steps`` (``_kernels.teacher_gradient``, every task
        in this thread), else by ``teacher_objective``'s passes."""
        operator = self.operator(data)
        if not self.compiles_theta_steps():
            value, _, d_transitions = self.teacher_objective(operator, data, need_transitions=True)
            assert d_transitions is not None
            return value, d_transitions
        passes, d_probs = self._teacher_pass_arguments(operator, data, fresh_rows=False)
        demo_values, step_values, code = _kernels.teacher_gradient(passes)
        value = self._teacher_value(demo_values, step_values, code, self._q_shape(operator, data))
        return value, d_probs.astype(np.float64).reshape(
            operator.num_states, operator.num_actions, operator.width
        )

    def _teacher_pass_arguments(
        self, operator: TransitionOperator, data: TeacherData, fresh_rows: bool
    ) -> tuple[TeacherPasses, np.ndarray]:
        """``_kernels.teacher_gradient``'s arguments for the learner's rewards on ``operator``
        (with ``fresh_rows``, the passes' probabilities in arrays of their own, for a kernel to
        fill), and the dL/dT it writes."""
        settings = self.settings
        dtype = PRECISIONS[settings["planner_precision"]]
        horizon = check_horizon(self.env.horizon)
        rewards = self.task_rewards(data, self.costs)
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

    @staticmethod
    def _teacher_value(
        demo_values: np.ndarray, step_values: np.ndarray, code: int, shape: tuple[int, ...]
    ) -> float:
        """The teacher data's log-likelihood from a compiled gradient's records' values,
        summed as data_log_likelihood sums them; its error raised."""
        if code == LIKELIHOOD_NOT_FINITE:
            raise FloatingPointError("the teacher data's log-likelihood is not finite (Q is not)")
        refuse(int(code), shape)
        value = float(demo_values.sum()) + (
            float(step_values.sum()) if step_values.shape[0] else 0.0
        )
        if not np.isfinite(value):
            raise FloatingPointError("the teacher data's log-likelihood is not finite (Q is not)")
        return value

    def theta_steps(
        self,
        observed: ObservedTransitions,
        steps: int,
        data: TeacherData | None = None,
        d_transitions: np.ndarray | None = None,
    ) -> float:
        """``steps`` momentum steps on theta for the observed transitions' likelihood and the
        dynamics prior, plus (BAM's step) the teacher data's gradient ``d_transitions`` on the
        table of ``operator(data)`` pulled back to theta; by the setting's gradient rule. In one
        compiled call where ``compiles_theta_steps`` (``_kernels.theta_steps``), else step by
        step. Returns the likelihood plus prior at the last step's start (0 without steps)."""
        if steps <= 0:
            return 0.0
        if not self.compiles_theta_steps():
            value = 0.0
            for _ in range(steps):
                value, grad = self.transition_objective(self.theta, observed, exact=False)
                if data is not None and d_transitions is not None:
                    grad = grad + self.pullback(data, d_transitions, exact=False)
                self.theta_step(grad)
            return value
        # A step's arithmetic is a few microseconds, which the NumPy calls of the likelihood,
        # the pull-back and the momentum step made about 50 (wall's BAM update: 140 steps).
        model = self._theta_model(observed, data)
        if d_transitions is None:
            d_teacher = np.empty(0)
        else:
            flat = np.ascontiguousarray(d_transitions, dtype=np.float64).reshape(-1)
            d_teacher = flat[self.plan_model(data).flat_parametric_entries]
        theta = np.array(self.theta, dtype=np.float64)  # copies: kept only if every step ends
        velocity = np.array(self.theta_optimizer.velocity, dtype=np.float64)
        value, code, row = _kernels.theta_steps(theta, velocity, model, int(steps), d_teacher)
        self._raise_theta_error(code, observed, row)
        self.theta, self.theta_optimizer.velocity = theta, velocity
        return float(value)

    def compiles_theta_steps(self) -> bool:
        """Whether ``theta_steps`` and ``teacher_gradient`` run compiled: the setting
        ``compiled_dynamics_steps``, where the model space's primitives are one the kernels
        know."""
        return (
            bool(self.settings["compiled_dynamics_steps"])
            and _primitive_family(self.env.model) is not None
        )

    def _theta_model(
        self, observed: ObservedTransitions, data: TeacherData | None
    ) -> tuple[Any, ...]:
        """What ``_kernels.theta_steps`` and ``_kernels.dynamics_steps`` read of the model space,
        the observed transitions, the teacher's table, the prior and the optimiser (``model``,
        as ``theta_steps`` describes it)."""
        model = self.env.model
        family = _primitive_family(model)
        assert family is not None
        authors = self.gradient_rule(exact=False) == "authors"
        teacher = self.plan_model(data)
        sd = self.settings["dynamics_prior_sd"]
        if sd is None:
            sd = model.prior_sd
        if sd is not None and (not np.isfinite(sd) or sd <= 0):  # as gaussian_log_prior refuses it
            raise ValueError(f"prior standard deviation must be positive, got {sd!r}")
        bound = model.parameter_bound
        optimizer = self.theta_optimizer
        moved, taught = model.moved_entries, teacher.moved_entries
        return (
            *family,
            (
                observed.const, observed.coef, observed.index, observed.entry_rows,
                observed.moved_places, observed.moved_rows, observed.first_outcomes,
                observed.first_index,
            ),
            len(observed.rows),
            authors and model.outcomes is not None,
            moved.coef,
            moved.index,
            (taught.const, taught.coef, taught.index, taught.outcomes),
            authors and teacher.outcomes is not None,
            model.initial_value,
            0.0 if sd is None else float(sd) ** 2,
            (
                optimizer.learning_rate, optimizer.momentum, optimizer.max_step,
                optimizer.clip == "step", np.inf if bound is None else float(bound),
            ),
        )  # fmt: skip

    @staticmethod
    def _q_shape(operator: TransitionOperator, data: TeacherData) -> tuple[int, ...]:
        return (len(data.tasks), operator.num_states, operator.num_actions)

    @staticmethod
    def _raise_theta_error(code: int, observed: ObservedTransitions, row: int) -> None:
        if code == IMPOSSIBLE_TRANSITION:
            raise ValueError(
                f"observed transition {tuple(int(x) for x in observed.rows[row])} is "
                "impossible under the model space"
            )
        if code == GRADIENT_NOT_FINITE:
            raise FloatingPointError("the objective's gradient is not finite")

    def dynamics_steps_in_one_call(
        self, data: TeacherData, observed: ObservedTransitions, steps: int
    ) -> tuple[float, int]:
        """Up to ``steps`` of BAM's dynamics steps (the teacher's gradient and the step on
        theta) in one call of ``_kernels.dynamics_steps``, the table at each theta made and
        laid out for the passes in it (where ``_dynamics_step`` made them in NumPy: about 50
        microseconds a step); every task planned in this thread. Returns the objective besides
        the costs' prior at the last step's start and the steps taken: fewer where a table's
        zeros left the passes' layouts, for the caller to take the rest."""
        operator = self.operator(data)
        layout = operator.layout
        assert layout is not None
        teacher = self.plan_model(data)
        model = self._theta_model(observed, data)
        passes, _ = self._teacher_pass_arguments(operator, data, fresh_rows=True)
        theta = np.array(self.theta, dtype=np.float64)
        velocity = np.array(self.theta_optimizer.velocity, dtype=np.float64)
        kernel_arguments = (
            theta,
            velocity,
            model,
            int(steps),
            operator.probs_flat.copy(),
            teacher.flat_parametric_entries,
            layout.nonzero,
            (layout.shifted_source, layout.flat_source, layout.dense_source, layout.target_source),
            passes,
        )
        value, demo_values, step_values, code, done, row = _kernels.dynamics_steps(
            *kernel_arguments
        )
        if code not in (0, LAYOUT_CHANGED):
            self._raise_theta_error(code, observed, row)
            self._teacher_value(demo_values, step_values, code, self._q_shape(operator, data))
        self.theta, self.theta_optimizer.velocity = theta, velocity
        if done == 0:
            return float("nan"), 0
        teacher_value = self._teacher_value(demo_values, step_values, 0, ())
        return float(value) + teacher_value, int(done)

    def cost_gradient(self, d_rewards: np.ndarray) -> np.ndarray:
        """dL/d(per-cell costs) of tasks with data from dL/d(per-state rewards): 0 on the cells
        that carry no cost."""
        return cell_gradient(self.env, d_rewards) * self.cost_mask

    def task_rewards(self, data: TeacherData, costs: np.ndarray) -> np.ndarray:
        """Rewards (tasks with data, S) for the planner; subclasses add a global cost."""
        return cell_rewards(self.env, costs[data.tasks])

    def teacher_objective(
        self,
        operator: TransitionOperator,
        data: TeacherData,
        need_transitions: bool,
    ) -> tuple[float, np.ndarray, np.ndarray | None]:
        """Teacher-data log-likelihood, dL/d(per-state rewards of tasks with data), dL/dT
        (on the table of ``operator(data)``)."""
        rewards = self.task_rewards(data, self.costs)
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

    def cost_step(self, operator: TransitionOperator, data: TeacherData) -> float:
        """One momentum step on the costs (tasks with data); returns the objective before it."""
        value, d_rewards, _ = self.teacher_objective(operator, data, need_transitions=False)
        grad = np.zeros_like(self.costs)
        grad[data.tasks] = self.cost_gradient(d_rewards)
        prior, prior_grad = self.cost_prior(self.costs)
        bound = self.settings["cost_bound"]
        updated = self.cost_optimizer.step(self.costs.ravel(), (grad + prior_grad).ravel())
        self.costs = np.clip(updated.reshape(self.costs.shape), -bound, bound)
        return value + prior

    def cost_steps(self, operator: TransitionOperator, data: TeacherData, steps: int) -> float:
        """``steps`` momentum steps on the costs (tasks with data), in one compiled call where
        ``compiles_cost_steps`` (``_compiled_cost_steps``), else step by step; returns the
        objective before the last."""
        if steps <= 0:
            return float("nan")
        if self.compiles_cost_steps():
            return self._compiled_cost_steps(operator, data, steps)
        value = float("nan")
        for _ in range(steps):
            value = self.cost_step(operator, data)
        return value

    def compiles_cost_steps(self) -> bool:
        """Whether ``cost_steps`` runs compiled: the setting ``compiled_steps``, where each
        task's costs have an optimiser of their own."""
        return bool(self.settings["compiled_steps"]) and self.cost_optimizer.rows == len(
            self.env.tasks
        )

    def _compiled_cost_steps(
        self, operator: TransitionOperator, data: TeacherData, steps: int
    ) -> float:
        """``cost_step`` ``steps`` times, the tasks' steps in one compiled call each
        (``_kernels.cost_steps_tasks``, the tasks split over the planner's threads as a pass's
        are): a step's arithmetic outside its two passes is a few microseconds, which a NumPy
        call per operation made about a hundred (wall: over half of an update)."""
        env, settings = self.env, self.settings
        dtype = PRECISIONS[settings["planner_precision"]]
        actions, feedback = action_model(settings), feedback_model(settings)
        horizon = check_horizon(env.horizon)
        optimizer = self.cost_optimizer
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
        costs = np.array(self.costs, dtype=np.float64)  # copies: kept only if every step ends
        velocity = np.array(optimizer.velocity, dtype=np.float64).reshape(costs.shape)
        before = np.empty_like(costs)
        demo_values = np.zeros(data.demo_tasks.shape[0])
        step_values = np.zeros(data.step_tasks.shape[0])
        codes = np.zeros(len(env.tasks), dtype=np.int64)
        bound = float(settings["cost_bound"])
        prior_sd = float(settings["cost_prior_sd"])
        if not np.isfinite(prior_sd) or prior_sd <= 0:  # as gaussian_log_prior refuses it
            raise ValueError(f"prior standard deviation must be positive, got {prior_sd!r}")
        cells = CostCells(
            data_row, plan_states, env.state_cells.astype(np.int64), int(env.num_features),
            self.cost_mask.astype(np.float64),
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
        planning.run_pass(  # by the module, as the passes' are: a benchmark counts them there
            task_chunks(len(env.tasks)),
            _kernels.cost_steps_tasks,
            _kernels.cost_steps_chunks,
            (
                *operator.pass_layouts(dtype), NO_GRADIENT[dtype], dtype(actions.beta), horizon,
                cells, records, models, int(steps), prior_sd**2, step_settings, trace, workspace,
                state,
            ),
        )  # fmt: skip
        for code in codes[codes != 0]:
            if code == GRADIENT_NOT_FINITE:
                raise FloatingPointError("the objective's gradient is not finite")
            if code == LIKELIHOOD_NOT_FINITE:
                raise FloatingPointError(
                    "the teacher data's log-likelihood is not finite (Q is not)"
                )
            refuse(int(code), (num_data, num_plan, env.num_actions))
        self.costs, optimizer.velocity = costs, velocity.reshape(-1)
        # The objective at the last step's start, summed as the NumPy steps sum it.
        value = float(demo_values.sum()) + (
            float(step_values.sum()) if step_values.shape[0] else 0.0
        )
        prior = float(-0.5 * ((before - 0.0) ** 2).sum() / prior_sd**2)
        return value + prior

    # -- L-BFGS-B fitting over packed parameter vectors ------------------------------------
    def cost_vector(self, data: TeacherData) -> np.ndarray:
        """The cost parameters that the teacher data informs, packed into one vector."""
        return self.costs[data.tasks].ravel().copy()

    def set_cost_vector(self, data: TeacherData, vector: np.ndarray) -> None:
        costs = self.costs.copy()
        costs[data.tasks] = vector[: len(data.tasks) * self.env.num_cells].reshape(
            len(data.tasks), self.env.num_cells
        )
        self.costs = costs

    def theta_bounds(self) -> list[tuple[float | None, float | None]]:
        """L-BFGS-B's box for the dynamics parameters: its line search may try points far
        out, where a logit saturates and an observed transition gets probability 0 (log -inf;
        seen in three-rooms and three-fields with feedback). Within +-15 every probability of
        the model space, and one minus it (a move that fails when a machine works with
        probability p), stays above 1e-13; the momentum schedule's clipped steps never get
        near."""
        return [(-THETA_BOUND, THETA_BOUND)] * self.env.model.num_parameters

    def cost_bounds(self, data: TeacherData) -> list[tuple[float | None, float | None]]:
        bound = float(self.settings["cost_bound"])
        return [(-bound, bound)] * len(self.cost_vector(data))

    def packed_cost_gradient(
        self, data: TeacherData, d_rewards: np.ndarray
    ) -> tuple[float, np.ndarray]:
        """Cost priors and the gradient of (teacher likelihood + priors) in the packed layout."""
        prior, prior_grad = self.cost_prior(self.costs[data.tasks])
        return prior, (self.cost_gradient(d_rewards) + prior_grad).ravel()

    def fit_costs_lbfgs(
        self, operator: TransitionOperator, data: TeacherData, evaluations: int
    ) -> tuple[float, int]:
        """Costs by L-BFGS-B under a fixed dynamics model; returns (objective, evaluations)."""

        def objective(vector: np.ndarray) -> tuple[float, np.ndarray]:
            self.set_cost_vector(data, vector)
            value, d_rewards, _ = self.teacher_objective(operator, data, need_transitions=False)
            prior, grad = self.packed_cost_gradient(data, d_rewards)
            return value + prior, grad

        best, value, evaluations = maximize_lbfgs(
            objective,
            self.cost_vector(data),
            self.cost_bounds(data),
            evaluations,
        )
        self.set_cost_vector(data, best)
        return value, evaluations

    def fit_theta_lbfgs(self, observed: ObservedTransitions, evaluations: int) -> tuple[float, int]:
        """Dynamics by L-BFGS-B on the observed transitions and the prior alone."""
        best, value, evaluations = maximize_lbfgs(
            lambda theta: self.transition_objective(theta, observed),
            self.theta.copy(),
            self.theta_bounds(),
            evaluations,
        )
        self.theta = best
        return value, evaluations

    def objective(self) -> tuple[float, dict[str, np.ndarray]]:
        """Equation (5) at the current parameters over all recorded data, with its gradient
        for every parameter block (used by tests and to compare optimisers)."""
        data = self.teacher_data()
        value, d_theta = self.transition_objective(self.theta, self.data.observed_transitions())
        d_costs = np.zeros_like(self.costs)
        d_rewards = np.zeros((0, self.env.num_states))
        if not data.empty:
            teacher, d_rewards, d_transitions = self.teacher_objective(
                self.operator(data), data, need_transitions=True
            )
            assert d_transitions is not None
            value += teacher
            d_theta = d_theta + self.pullback(data, d_transitions)
            d_costs[data.tasks] = self.cost_gradient(d_rewards)
        prior, prior_grad = self.cost_prior(self.costs)
        gradients = {"theta": d_theta, "costs": d_costs + prior_grad}
        extra_value, extra = self._extra_objective(d_rewards)
        gradients.update(extra)
        return value + prior + extra_value, gradients

    def _extra_objective(self, d_rewards: np.ndarray) -> tuple[float, dict[str, np.ndarray]]:
        """Objective terms and gradients of parameter blocks a subclass adds."""
        return 0.0, {}

    # -- persistence ----------------------------------------------------------------------
    def _parameters_state(self) -> dict[str, np.ndarray]:
        return {
            "theta": self.theta.copy(),
            "costs": self.costs.copy(),
            "theta_velocity": self.theta_optimizer.velocity.copy(),
            "cost_velocity": self.cost_optimizer.velocity.copy(),
            "fitted_tasks": self.fitted_tasks.copy(),
        }

    def _load_parameters_state(self, state: dict[str, Any]) -> None:
        self.theta = self.env.model.check_parameters(state["theta"]).copy()
        costs = check_finite("costs", state["costs"])
        if costs.shape != self.costs.shape:
            raise ValueError(f"costs must have shape {self.costs.shape}, got {costs.shape}")
        self.costs = costs.copy()
        self.theta_optimizer.velocity = check_finite(
            "theta velocity", state["theta_velocity"]
        ).copy()
        self.cost_optimizer.velocity = check_finite("cost velocity", state["cost_velocity"]).copy()
        if "fitted_tasks" in state:
            fitted = np.asarray(state["fitted_tasks"], dtype=bool)
            if fitted.shape != self.fitted_tasks.shape:
                raise ValueError(f"fitted tasks must have shape {self.fitted_tasks.shape}")
        else:  # saved before the schedule existed: every task with data was fitted
            fitted = np.zeros_like(self.fitted_tasks)
            if self.updates > 0:
                fitted[taught_tasks(self.data)] = True
        self.fitted_tasks = fitted.copy()
        self._policies = None

    def update(self):  # type: ignore[override]
        self._policies = None
        result = super().update()
        self.fitted_tasks[taught_tasks(self.data)] = True
        return result


def _primitive_family(model: TransitionModel) -> tuple[int, int] | None:
    """The model space's primitives as ``_kernels.theta_steps`` takes them (the family and
    a softmax row's length), or None for a model space it does not know."""
    if type(model) is SigmoidModel:
        return _kernels.SIGMOID_PRIMITIVES, 1
    if type(model) is SoftmaxRowsModel:
        return _kernels.SOFTMAX_ROWS_PRIMITIVES, model.choices
    return None


def _own_probabilities(layout: Any, dtype: type) -> Any:
    """A pass layout whose probabilities (its arrays in the passes' precision) are copies, for
    a kernel to fill; its index arrays shared."""
    return layout._make(a.copy() if a.dtype == dtype else a for a in layout)


def _rows_by_task(tasks: np.ndarray, num_tasks: int) -> tuple[np.ndarray, np.ndarray]:
    """The records' places grouped by task, each task's in the data's order, and where each
    task's begin (``num_tasks + 1`` bounds)."""
    rows = np.argsort(tasks, kind="stable").astype(np.int64)
    start = np.searchsorted(tasks[rows], np.arange(num_tasks + 1)).astype(np.int64)
    return rows, start
