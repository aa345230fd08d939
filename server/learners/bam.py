"""Behavior Aware Modeling (section 3.1): maximise equation (5) over the dynamics parameters
theta and every task's costs, alternating cost steps and dynamics steps. The dynamics steps use
the observed transitions AND the teacher's data through the planner, which is how BAM learns
about dynamics the teacher knows but the agent never observed (the doorway's walls)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from server.domains.base import ObservedTransitions
from server.learners import _kernels
from server.learners.cost_fit import q_shape, teacher_value
from server.learners.likelihoods import LAYOUT_CHANGED
from server.learners.objective import TeacherData, maximize_lbfgs
from server.learners.planner_learner import PlannerLearner
from server.learners.settings import (
    CompiledPlannerSteps,
    PlannerSettings,
    check_non_negative_count,
    setting,
    setting_of,
)


@dataclass(frozen=True, kw_only=True)
class BAMSettings(PlannerSettings, CompiledPlannerSteps):
    """BAM's settings: its schedule of alternations (the planner learners' settings besides)."""

    alternations: int = setting(
        10, "An update's alternations of [cost steps, then dynamics steps] (the authors')."
    )
    cost_steps: int = setting_of(
        PlannerSettings, "cost_steps", 20, "Momentum steps on the costs in each alternation."
    )
    dynamics_steps: int = setting_of(
        PlannerSettings,
        "dynamics_steps",
        20,
        "Momentum steps on the dynamics parameters in each alternation.",
    )
    warm_alternations: int = setting(
        0,
        'With optimizer "warm-lbfgs": alternations of the momentum schedule that a warm update '
        "runs before L-BFGS-B (0: L-BFGS-B alone). Two reach at least the reference "
        "schedule's value of equation (5) at about a third of its passes, but the agents learn "
        'less well (docs/defaults.md, "A faster optimiser"): a setting, not the default.',
        check=check_non_negative_count,
    )
    # A warm update runs 7 of the 10 alternations (5 learn less in navigation, beyond the
    # demonstrations experiment's chance: docs/defaults.md, "Shorter warm updates").
    warm_share: float = setting_of(PlannerSettings, "warm_share", 0.7)


class BAM(PlannerLearner):
    """Behavior Aware Modeling, ``learners.make("bam", env)`` (the module docstring): an
    update alternates the cost fit's steps and the dynamics fit's, both through the planner."""

    name = "bam"
    settings_type: ClassVar[type[PlannerSettings]] = BAMSettings
    warm_up_settings = {"alternations": 1, **PlannerLearner.warm_up_settings}

    @property
    def bam_settings(self) -> BAMSettings:
        """``settings``, as BAM's."""
        settings = self.settings
        assert isinstance(settings, BAMSettings)
        return settings

    def _fit(self) -> tuple[float, int]:
        settings = self.bam_settings
        data = self.teacher_data()
        observed = self.env.model.observe(self.data.observed_transitions())
        optimizer, evaluations = self.schedule(data)
        if optimizer == "momentum":
            alternations = self.momentum_steps(int(settings.alternations), data)
            return self._fit_momentum(data, observed, alternations)
        steps = 0
        if settings.optimizer == "warm-lbfgs" and settings.warm_alternations:
            self.stop_momentum()
            _, steps = self._fit_momentum(data, observed, int(settings.warm_alternations))
        objective, evaluations = self._fit_lbfgs(data, observed, evaluations)
        return objective, steps + evaluations

    def _fit_momentum(
        self, data: TeacherData, observed: ObservedTransitions, alternations: int
    ) -> tuple[float, int]:
        """``alternations`` of [cost steps, then dynamics steps] (the reference schedule)."""
        steps = 0
        objective = float("nan")
        for _ in range(alternations):
            if not data.empty:
                cost_steps = int(self.settings.cost_steps)
                self.cost_fit.steps(self.operator(data), data, cost_steps)
                steps += cost_steps
            # The dynamics steps leave the costs as they are, and their prior with them.
            cost_prior, _ = self.cost_fit.prior(self.costs)
            remaining = int(self.settings.dynamics_steps)
            while remaining > 0 and not data.empty and self.dynamics_fit.compiled:
                value, done = self.dynamics_steps_in_one_call(data, observed, remaining)
                if done:
                    objective = value + cost_prior
                    remaining -= done
                    steps += done
                if remaining:  # a table's zeros left the passes' layouts: one step here
                    objective = self._dynamics_step(data, observed, cost_prior)
                    remaining -= 1
                    steps += 1
            for _ in range(remaining):
                objective = self._dynamics_step(data, observed, cost_prior)
                steps += 1
        return objective, steps

    def _fit_lbfgs(
        self, data: TeacherData, observed: ObservedTransitions, evaluations: int
    ) -> tuple[float, int]:
        """Equation (5) over theta and the informed costs jointly with L-BFGS-B."""
        dynamics, costs = self.dynamics_fit, self.cost_fit
        if data.empty:
            return dynamics.fit_lbfgs(observed, evaluations)
        num_theta = self.env.model.num_parameters

        def objective(vector: np.ndarray) -> tuple[float, np.ndarray]:
            self.theta = vector[:num_theta]
            costs.set_vector(data, vector[num_theta:])
            value, d_theta = dynamics.transition_objective(self.theta, observed)
            teacher, d_rewards, d_transitions = costs.teacher_objective(
                self.operator(data), data, need_transitions=True
            )
            assert d_transitions is not None
            d_theta = d_theta + self.pullback(data, d_transitions)
            prior, d_costs = costs.packed_gradient(data, d_rewards)
            return value + teacher + prior, np.concatenate([d_theta, d_costs])

        start = np.concatenate([self.theta, costs.vector(data)])
        bounds = dynamics.bounds() + costs.bounds(data)
        best, value, used = maximize_lbfgs(objective, start, bounds, evaluations)
        self.theta = best[:num_theta].copy()
        costs.set_vector(data, best[num_theta:])
        return value, used

    def _dynamics_step(
        self, data: TeacherData, observed: ObservedTransitions, cost_prior: float
    ) -> float:
        """One momentum step on theta for the whole of equation (5), whose costs' prior is
        ``cost_prior``; returns the objective before the step."""
        if data.empty:
            return self.dynamics_fit.steps(observed, 1) + cost_prior
        teacher, d_transitions = self.teacher_gradient(data)
        value = self.dynamics_fit.steps(observed, 1, self.plan_model(data), d_transitions)
        return value + teacher + cost_prior

    def dynamics_steps_in_one_call(
        self, data: TeacherData, observed: ObservedTransitions, steps: int
    ) -> tuple[float, int]:
        """Up to ``steps`` of BAM's dynamics steps (the teacher's gradient and the step on
        theta) in one call of ``_kernels.dynamics_steps``, the table at each theta made and
        laid out for the passes in it (where ``_dynamics_step`` made them in NumPy: about 50
        microseconds a step); every task planned in this thread. Returns the objective besides
        the costs' prior at the last step's start and the steps taken: fewer where a table's
        zeros left the passes' layouts, for the caller to take the rest."""
        dynamics = self.dynamics_fit
        operator = self.operator(data)
        layout = operator.layout
        assert layout is not None
        teacher = self.plan_model(data)
        model = dynamics.kernel_model(observed, teacher)
        passes, _ = self.cost_fit.teacher_pass_arguments(operator, data, fresh_rows=True)
        theta = np.array(self.theta, dtype=np.float64)
        velocity = np.array(dynamics.optimizer.velocity, dtype=np.float64)
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
            dynamics.raise_error(code, observed, row)
            teacher_value(demo_values, step_values, code, q_shape(operator, data))
        self.theta, dynamics.optimizer.velocity = theta, velocity
        if done == 0:
            return float("nan"), 0
        return float(value) + teacher_value(demo_values, step_values, 0, ()), int(done)
