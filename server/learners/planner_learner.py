"""Base of the learners that act on a learned dynamics model and learned per-cell costs through
the soft planner: BAM, model-based IRL and model-based IRL with a global cost.

A planner learner composes a dynamics fit and a cost fit (``server.learners.fits``, their
public protocol: ``dynamics_fit.ThetaFit`` and ``cost_fit.CellCosts``) and keeps what the three
learners share: the optimiser schedule, the planning and the greedy policy, equation (5) with
its gradient, and the saved state. Each learner's ``_fit`` schedules the two fits."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from server.domains.base import Environment, TransitionModel
from server.learners.base import Learner, UpdateResult
from server.learners.cost_fit import CellCosts
from server.learners.dynamics_fit import ThetaFit
from server.learners.fits import CostFit, DynamicsFit
from server.learners.objective import TeacherData, taught_tasks
from server.learners.planning import TransitionOperator, soft_plan
from server.learners.settings import PlannerSettings, Settings


class PlannerLearner(Learner):
    """Learned dynamics parameters theta (the environment's model space, ``dynamics_fit``) and
    per-cell reward parameters per task (the paper's cost C = -reward, ``cost_fit``), acting
    greedily on soft Q."""

    settings_type: ClassVar[type[PlannerSettings]] = PlannerSettings
    warm_up_settings = {"cost_steps": 1, "dynamics_steps": 1}

    def __init__(self, env: Environment, seed: int = 0, **settings: Any) -> None:
        super().__init__(env, seed, **settings)
        self.dynamics_fit: DynamicsFit = ThetaFit(env, self.settings)
        self.cost_fit: CostFit = self.make_cost_fit()
        # Tasks whose costs an update has fitted (a task's first fit is a cold start).
        self.fitted_tasks = np.zeros(len(env.tasks), dtype=bool)
        self._policies: np.ndarray | None = None

    def make_cost_fit(self) -> CostFit:
        """The learner's cost fit: per-cell costs (global cost adds its global cost)."""
        return CellCosts(self.env, self.settings)

    @property
    def settings(self) -> PlannerSettings:
        """The learner's settings; settings given later are the fits' too."""
        return self._settings

    @settings.setter
    def settings(self, settings: Settings) -> None:
        if not isinstance(settings, PlannerSettings):
            raise TypeError(f"a planner learner's settings are PlannerSettings, not {settings!r}")
        self._settings = settings
        for fit in (self.__dict__.get("dynamics_fit"), self.__dict__.get("cost_fit")):
            if fit is not None:
                fit.settings = settings

    # -- the parameters: the fits' -----------------------------------------------------------
    @property
    def theta(self) -> np.ndarray:
        """The dynamics parameters (``dynamics_fit.theta``)."""
        return self.dynamics_fit.theta

    @theta.setter
    def theta(self, theta: np.ndarray) -> None:
        self.dynamics_fit.theta = theta

    @property
    def costs(self) -> np.ndarray:
        """Per-cell costs (tasks, cells) (``cost_fit.costs``)."""
        return self.cost_fit.costs

    @costs.setter
    def costs(self, costs: np.ndarray) -> None:
        self.cost_fit.costs = costs

    # -- the optimiser schedule -------------------------------------------------------------
    def schedule(self, data: TeacherData) -> tuple[str, int]:
        """This update's optimiser, "momentum" or "lbfgs", and its L-BFGS-B evaluation cap."""
        optimizer = self.settings.optimizer
        if optimizer == "lbfgs":
            return "lbfgs", int(self.settings.max_evaluations)
        if optimizer == "warm-lbfgs":
            if self.warm(data):
                return "lbfgs", int(self.settings.warm_evaluations)
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
        return min(steps, max(1, round(steps * float(self.settings.warm_share))))

    def stop_momentum(self) -> None:
        """Momentum steps from rest next: the velocity of earlier momentum steps is stale
        after L-BFGS-B has moved the parameters."""
        self.dynamics_fit.stop_momentum()
        self.cost_fit.stop_momentum()

    # -- the model ------------------------------------------------------------------------
    def rewards(self) -> np.ndarray:
        """Per-state rewards (tasks, S) the learner currently believes in."""
        return self.cost_fit.rewards()

    def operator(self, data: TeacherData | None = None) -> TransitionOperator:
        """The learned model's table at theta: over the states ``data`` plans on (see
        ``TeacherData.restricted``), or all states."""
        # dL/dT is only ever pulled back to theta, which reads the entries theta moves.
        return TransitionOperator.of_model(self.plan_model(data), self.theta)

    def teacher_data(self) -> TeacherData:
        """The recorded teacher data, planned over the states it can reach."""
        return TeacherData.from_log(self.data).restricted(self.env.model)

    def plan_model(self, data: TeacherData | None) -> TransitionModel:
        """The model ``data`` is planned on: its restricted model, or the environment's."""
        if data is None or data.plan_model is None:
            return self.env.model
        return data.plan_model

    def pullback(
        self, data: TeacherData, d_transitions: np.ndarray, exact: bool = True
    ) -> np.ndarray:
        """A gradient on the table of ``operator(data)``, pulled back to theta (with
        ``exact=False``, by the setting's gradient rule)."""
        return self.dynamics_fit.pullback(self.plan_model(data), d_transitions, exact)

    def teacher_gradient(self, data: TeacherData) -> tuple[float, np.ndarray]:
        """The teacher data's log-likelihood and dL/dT on the table of ``operator(data)``: in
        one compiled call where the dynamics steps are compiled, else by the passes."""
        return self.cost_fit.teacher_gradient(
            self.operator(data), data, compiled=self.dynamics_fit.compiled
        )

    def q_values(self) -> np.ndarray:
        """Soft Q (tasks, S, A) under the learned model and rewards."""
        return soft_plan(
            self.operator(),
            self.rewards(),
            self.settings.beta,
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

    def objective(self) -> tuple[float, dict[str, np.ndarray]]:
        """Equation (5) at the current parameters over all recorded data, with its gradient
        for every parameter block (used by tests and to compare optimisers)."""
        dynamics, costs = self.dynamics_fit, self.cost_fit
        data = self.teacher_data()
        value, d_theta = dynamics.transition_objective(self.theta, self.data.observed_transitions())
        d_costs = np.zeros_like(self.costs)
        d_rewards = np.zeros((0, self.env.num_states))
        if not data.empty:
            teacher, d_rewards, d_transitions = costs.teacher_objective(
                self.operator(data), data, need_transitions=True
            )
            assert d_transitions is not None
            value += teacher
            d_theta = d_theta + self.pullback(data, d_transitions)
            d_costs[data.tasks] = costs.gradient(d_rewards)
        prior, prior_grad = costs.prior(self.costs)
        gradients = {"theta": d_theta, "costs": d_costs + prior_grad}
        extra_value, extra = costs.extra_objective(d_rewards)
        gradients.update(extra)
        return value + prior + extra_value, gradients

    # -- persistence ----------------------------------------------------------------------
    def _parameters_state(self) -> dict[str, np.ndarray]:
        return {
            **self.dynamics_fit.state(),
            **self.cost_fit.state(),
            "fitted_tasks": self.fitted_tasks.copy(),
        }

    def _load_parameters_state(self, state: dict[str, Any]) -> None:
        self.dynamics_fit.load_state(state)
        self.cost_fit.load_state(state)
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

    def update(self) -> UpdateResult:
        self._policies = None
        result = super().update()
        self.fitted_tasks[taught_tasks(self.data)] = True
        return result
