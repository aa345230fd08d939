"""Model-based IRL (section 4.1): fit T_theta to the observed transitions only (maximum
likelihood in the same model space as BAM), then fit each task's costs by ML-IRL under that
fixed model."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from server.learners.planner_learner import PlannerLearner
from server.learners.settings import CompiledPlannerSteps, PlannerSettings, setting_of


@dataclass(frozen=True, kw_only=True)
class ModelBasedSettings(PlannerSettings, CompiledPlannerSteps):
    """Model-based IRL's settings: the planner learners', with its own schedule."""

    dynamics_steps: int = setting_of(
        PlannerSettings,
        "dynamics_steps",
        200,
        "Momentum steps of an update's dynamics fit, on the observed transitions alone.",
    )
    cost_steps: int = setting_of(
        PlannerSettings,
        "cost_steps",
        200,
        "Momentum steps of an update's cost fit, under the fitted dynamics.",
    )
    # A warm update runs 100 of the 200 cost steps (docs/defaults.md, "Shorter warm
    # updates"; 50 kept the curves too, nearer the edge in the farming environments).
    warm_share: float = setting_of(PlannerSettings, "warm_share", 0.5)


class ModelBasedIRL(PlannerLearner):
    """Model-based IRL, ``learners.make("model-based", env)`` (the module docstring): an
    update runs the dynamics fit on the observed transitions, then the cost fit under it."""

    name = "model-based"
    # Its code reads the planner learners' settings alone (global cost's have no compiled steps).
    settings_type: ClassVar[type[PlannerSettings]] = ModelBasedSettings

    def _fit(self) -> tuple[float, int]:
        dynamics, costs = self.dynamics_fit, self.cost_fit
        observed = self.env.model.observe(self.data.observed_transitions())
        data = self.teacher_data()
        optimizer, evaluations = self.schedule(data)
        if self.settings.optimizer == "lbfgs":
            dynamics_objective, dynamics_evaluations = dynamics.fit_lbfgs(observed, evaluations)
        else:
            # The dynamics fit never runs the planner: the momentum schedule costs little.
            dynamics_objective = dynamics.steps(observed, int(self.settings.dynamics_steps))
            dynamics_evaluations = int(self.settings.dynamics_steps)
        if optimizer == "lbfgs":
            if data.empty:
                return dynamics_objective, dynamics_evaluations
            teacher_objective, cost_evaluations = costs.fit_lbfgs(
                self.operator(data), data, evaluations
            )
            return dynamics_objective + teacher_objective, dynamics_evaluations + cost_evaluations
        teacher_objective = 0.0
        cost_steps = 0
        if not data.empty:
            operator = self.operator(data)
            cost_steps = self.momentum_steps(int(self.settings.cost_steps), data)
            if cost_steps:
                teacher_objective = costs.steps(operator, data, cost_steps)
        steps = int(self.settings.dynamics_steps) + cost_steps
        return dynamics_objective + teacher_objective, steps
