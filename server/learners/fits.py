"""The public protocol of the planner learners' two collaborators: a dynamics fit
(``DynamicsFit``: the parameters theta of the environment's model space) and a cost fit
(``CostFit``: each task's per-cell costs). ``PlannerLearner`` composes one of each; BAM,
model-based IRL and global cost differ in how their ``_fit`` schedules the two (BAM alternates
them through the planner; model-based IRL fits the dynamics on the observed transitions alone,
then the costs under them) and global cost in its cost fit.

The implementations: ``dynamics_fit.ThetaFit``, ``cost_fit.CellCosts`` and
``global_cost.GlobalCellCosts``. The two fits meet only through the learner: the dynamics fit
makes the transition table the cost fit plans the teacher data on
(``PlannerLearner.operator``), and the cost fit's gradient on that table
(``CostFit.teacher_gradient``) goes back to the dynamics fit's steps, pulled back to theta.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from server.domains.base import ObservedTransitions, TransitionModel
from server.learners._kernels import TeacherPasses
from server.learners.objective import MomentumAscent, TeacherData
from server.learners.planning import TransitionOperator
from server.learners.settings import PlannerSettings

Bounds = list[tuple[float | None, float | None]]


class DynamicsFit(Protocol):
    """What a planner learner asks of its dynamics fit.

    ``theta`` holds the parameters and ``optimizer`` their momentum state; ``settings`` are the
    learner's (a learner given new settings hands them on). ``teacher`` arguments name the
    model whose table a teacher gradient is on (the data's restricted model, or the
    environment's); a gradient on that table is pulled back to theta by its ``pullback``."""

    theta: np.ndarray
    optimizer: MomentumAscent
    settings: PlannerSettings

    @property
    def compiled(self) -> bool:
        """Whether ``steps`` (and the teacher's gradient) run compiled."""
        ...

    def prior(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        """ln m(theta) and its gradient."""
        ...

    def transition_objective(
        self, theta: np.ndarray, observed: np.ndarray | ObservedTransitions, exact: bool = True
    ) -> tuple[float, np.ndarray]:
        """ln T_theta of the observed transitions plus ln m(theta), and the gradient."""
        ...

    def pullback(
        self, teacher: TransitionModel, d_transitions: np.ndarray, exact: bool = True
    ) -> np.ndarray:
        """A gradient on ``teacher``'s table at theta, pulled back to theta."""
        ...

    def step(self, grad: np.ndarray) -> None:
        """One momentum step on theta."""
        ...

    def steps(
        self,
        observed: ObservedTransitions,
        steps: int,
        teacher: TransitionModel | None = None,
        d_transitions: np.ndarray | None = None,
    ) -> float:
        """``steps`` momentum steps; the objective at the last one's start."""
        ...

    def kernel_model(
        self, observed: ObservedTransitions, teacher: TransitionModel | None
    ) -> tuple[Any, ...]:
        """What the compiled steps read of the model space, the data and the optimiser."""
        ...

    def raise_error(self, code: int, observed: ObservedTransitions, row: int) -> None:
        """The error a compiled step's ``code`` stands for, raised."""
        ...

    def fit_lbfgs(self, observed: ObservedTransitions, evaluations: int) -> tuple[float, int]:
        """theta by L-BFGS-B on the observed transitions and the prior alone."""
        ...

    def bounds(self) -> Bounds:
        """L-BFGS-B's box for theta."""
        ...

    def stop_momentum(self) -> None:
        """Momentum steps from rest next."""
        ...

    def state(self) -> dict[str, np.ndarray]:
        """theta and the velocity, copied (keys of the learner's saved state)."""
        ...

    def load_state(self, state: dict[str, Any]) -> None:
        """Inverse of ``state``, checked."""
        ...


class CostFit(Protocol):
    """What a planner learner asks of its cost fit.

    ``costs`` (tasks, cells) and ``optimizer`` are the per-cell costs and their momentum state;
    ``settings`` are the learner's (a learner given new settings hands them on). ``operator``
    arguments are the learned transition table the teacher data is planned on
    (``PlannerLearner.operator(data)``). The L-BFGS-B methods work on the packed vector of the
    parameters ``data`` informs."""

    costs: np.ndarray
    optimizer: MomentumAscent
    settings: PlannerSettings

    @property
    def compiled(self) -> bool:
        """Whether ``steps`` run compiled."""
        ...

    def rewards(self) -> np.ndarray:
        """Per-state rewards (tasks, S)."""
        ...

    def prior(self, costs: np.ndarray) -> tuple[float, np.ndarray]:
        """ln of the per-cell costs' prior and its gradient."""
        ...

    def gradient(self, d_rewards: np.ndarray) -> np.ndarray:
        """dL/d(per-cell costs) of the tasks with data from dL/d(per-state rewards)."""
        ...

    def teacher_objective(
        self, operator: TransitionOperator, data: TeacherData, need_transitions: bool
    ) -> tuple[float, np.ndarray, np.ndarray | None]:
        """The teacher data's log-likelihood, dL/d(rewards of the tasks with data) and dL/dT."""
        ...

    def teacher_gradient(
        self, operator: TransitionOperator, data: TeacherData, compiled: bool
    ) -> tuple[float, np.ndarray]:
        """The teacher data's log-likelihood and dL/dT on ``operator``'s table."""
        ...

    def teacher_pass_arguments(
        self, operator: TransitionOperator, data: TeacherData, fresh_rows: bool
    ) -> tuple[TeacherPasses, np.ndarray]:
        """The compiled teacher gradient's arguments, and the dL/dT it writes."""
        ...

    def steps(self, operator: TransitionOperator, data: TeacherData, steps: int) -> float:
        """``steps`` momentum steps; the objective before the last."""
        ...

    def vector(self, data: TeacherData) -> np.ndarray:
        """The parameters ``data`` informs, packed."""
        ...

    def set_vector(self, data: TeacherData, vector: np.ndarray) -> None:
        """Inverse of ``vector``."""
        ...

    def bounds(self, data: TeacherData) -> Bounds:
        """L-BFGS-B's box for ``vector``."""
        ...

    def packed_gradient(self, data: TeacherData, d_rewards: np.ndarray) -> tuple[float, np.ndarray]:
        """The priors, and the gradient of (teacher likelihood + priors), packed."""
        ...

    def fit_lbfgs(
        self, operator: TransitionOperator, data: TeacherData, evaluations: int
    ) -> tuple[float, int]:
        """The costs by L-BFGS-B on ``operator``'s table; (objective, evaluations)."""
        ...

    def extra_objective(self, d_rewards: np.ndarray) -> tuple[float, dict[str, np.ndarray]]:
        """Terms and gradients of parameter blocks besides ``costs`` (none, or the global cost)."""
        ...

    def stop_momentum(self) -> None:
        """Momentum steps from rest next."""
        ...

    def state(self) -> dict[str, np.ndarray]:
        """The parameters and velocities, copied (keys of the learner's saved state)."""
        ...

    def load_state(self, state: dict[str, Any]) -> None:
        """Inverse of ``state``, checked."""
        ...
