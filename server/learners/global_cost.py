"""Model-based IRL with a global cost (section 4.3): as model-based IRL, but every task's reward
is its own per-cell cost plus one cost over full states shared by all tasks, the simpler way to
share knowledge across tasks that BAM is compared against."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from server.domains.base import Environment, check_finite
from server.learners.cost_fit import CellCosts
from server.learners.likelihoods import gaussian_log_prior
from server.learners.model_based import ModelBasedIRL, ModelBasedSettings
from server.learners.objective import MomentumAscent, TeacherData, cell_rewards
from server.learners.planning import TransitionOperator
from server.learners.settings import PlannerSettings, setting, setting_of


@dataclass(frozen=True, kw_only=True)
class GlobalCostSettings(PlannerSettings):
    """Global cost's settings: model-based IRL's and the global cost's prior. On every update
    the authors' schedule (its experiment has not been run with shorter warm updates), and
    NumPy's steps (the global cost ties the tasks' cost steps together; the dynamics steps are
    kept for the same agents as its published runs): no compiled steps."""

    dynamics_steps: int = setting_of(ModelBasedSettings, "dynamics_steps", 200)
    cost_steps: int = setting_of(ModelBasedSettings, "cost_steps", 200)
    global_prior_sd: float = setting(
        1.0, "The deviation of the global cost's Gaussian prior N(0, sd), centred on 0."
    )
    warm_share: float = setting_of(PlannerSettings, "warm_share", 1.0)


class GlobalCellCosts(CellCosts):
    """Per-cell costs per task plus one cost over full states that every task shares
    (``fits.CostFit``): a task's reward is its own costs' plus the global cost. Its steps are
    NumPy's (the global cost's step joins the tasks')."""

    def __init__(self, env: Environment, settings: PlannerSettings) -> None:
        super().__init__(env, settings)
        self.global_costs = np.zeros(env.num_states)
        # "per-task" (the authors'): each task's costs and the global cost have an optimiser
        # of their own; "joint": one optimiser over [task costs, global cost].
        self.joint = settings.cost_optimizers == "joint"
        self.global_optimizer = MomentumAscent(
            (self.costs.size if self.joint else 0) + env.num_states,
            settings.cost_learning_rate,
            settings.momentum,
            settings.max_step,
            clip=settings.momentum_clip,
        )

    def rewards(self) -> np.ndarray:
        return cell_rewards(self.env, self.costs) + self.global_costs[None, :]

    def task_rewards(self, data: TeacherData) -> np.ndarray:
        return cell_rewards(self.env, self.costs[data.tasks]) + self.global_costs[None, :]

    @property
    def compiled(self) -> bool:
        return False  # the global cost's step joins the tasks' (``step`` below)

    def step(self, operator: TransitionOperator, data: TeacherData) -> float:
        value, d_rewards, _ = self.teacher_objective(operator, data, need_transitions=False)
        grad = np.zeros_like(self.costs)
        grad[data.tasks] = self.gradient(d_rewards)
        prior, prior_grad = self.prior(self.costs)
        global_prior, global_prior_grad = self.global_prior()
        global_grad = d_rewards.sum(axis=0) + global_prior_grad
        bound = self.settings.cost_bound
        if self.joint:
            joint = np.concatenate([self.costs.ravel(), self.global_costs])
            joint_grad = np.concatenate([(grad + prior_grad).ravel(), global_grad])
            updated = np.clip(self.global_optimizer.step(joint, joint_grad), -bound, bound)
            self.costs = updated[: self.costs.size].reshape(self.costs.shape)
            self.global_costs = updated[self.costs.size :]
        else:
            costs = self.optimizer.step(self.costs.ravel(), (grad + prior_grad).ravel())
            self.costs = np.clip(costs.reshape(self.costs.shape), -bound, bound)
            self.global_costs = np.clip(
                self.global_optimizer.step(self.global_costs, global_grad), -bound, bound
            )
        return value + prior + global_prior

    # L-BFGS-B packing: the informed task costs, then the global cost.
    def vector(self, data: TeacherData) -> np.ndarray:
        return np.concatenate([super().vector(data), self.global_costs])

    def set_vector(self, data: TeacherData, vector: np.ndarray) -> None:
        super().set_vector(data, vector)
        self.global_costs = vector[len(data.tasks) * self.env.num_cells :].copy()

    def packed_gradient(self, data: TeacherData, d_rewards: np.ndarray) -> tuple[float, np.ndarray]:
        prior, grad = super().packed_gradient(data, d_rewards)
        global_prior, global_grad = self.global_prior()
        return prior + global_prior, np.concatenate([grad, d_rewards.sum(axis=0) + global_grad])

    def extra_objective(self, d_rewards: np.ndarray) -> tuple[float, dict[str, np.ndarray]]:
        prior, prior_grad = self.global_prior()
        return prior, {"global_costs": d_rewards.sum(axis=0) + prior_grad}

    def global_prior(self) -> tuple[float, np.ndarray]:
        """ln of the global cost's prior N(0, ``global_prior_sd``) and its gradient."""
        settings = self.settings
        assert isinstance(settings, GlobalCostSettings)
        return gaussian_log_prior(self.global_costs, 0.0, settings.global_prior_sd)

    def stop_momentum(self) -> None:
        super().stop_momentum()
        self.global_optimizer.velocity[:] = 0.0

    def state(self) -> dict[str, np.ndarray]:
        return {
            **super().state(),
            "global_costs": self.global_costs.copy(),
            "global_velocity": self.global_optimizer.velocity.copy(),
        }

    def load_state(self, state: dict[str, Any]) -> None:
        super().load_state(state)
        global_costs = check_finite("global costs", state["global_costs"])
        if global_costs.shape != (self.env.num_states,):
            raise ValueError(f"global costs must have shape ({self.env.num_states},)")
        self.global_costs = global_costs.copy()
        if "global_velocity" in state:
            velocity = check_finite("global velocity", state["global_velocity"])
            if velocity.shape != self.global_optimizer.velocity.shape:
                raise ValueError(
                    f"global velocity must have shape {self.global_optimizer.velocity.shape}"
                )
            self.global_optimizer.velocity = velocity.copy()


class GlobalCostIRL(ModelBasedIRL):
    """Model-based IRL with a global cost, ``learners.make("global-cost", env)`` (the module
    docstring): model-based IRL's schedule, with ``GlobalCellCosts`` as its cost fit."""

    name = "global-cost"
    settings_type: ClassVar[type[PlannerSettings]] = GlobalCostSettings

    def make_cost_fit(self) -> GlobalCellCosts:
        return GlobalCellCosts(self.env, self.settings)

    @property
    def global_costs(self) -> np.ndarray:
        """The cost over full states every task shares (``cost_fit.global_costs``)."""
        return self._global_fit().global_costs

    @global_costs.setter
    def global_costs(self, costs: np.ndarray) -> None:
        self._global_fit().global_costs = costs

    def _global_fit(self) -> GlobalCellCosts:
        fit = self.cost_fit
        assert isinstance(fit, GlobalCellCosts)
        return fit
