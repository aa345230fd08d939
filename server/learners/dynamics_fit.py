"""The dynamics fit of the planner learners: the parameters theta of the environment's model
space, their prior ln m(theta), the likelihood of the observed transitions, and the momentum
and L-BFGS-B steps on them (BAM's steps add the teacher data's gradient, pulled back to theta).

``ThetaFit`` implements ``fits.DynamicsFit``, the protocol a planner learner composes
(``PlannerLearner.dynamics_fit``). It knows no costs: a gradient of the teacher
data's likelihood on a transition table comes in from the caller (``CostFit.teacher_gradient``).
"""

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
)
from server.learners import _kernels
from server.learners.fits import Bounds
from server.learners.likelihoods import (
    GRADIENT_NOT_FINITE,
    IMPOSSIBLE_TRANSITION,
    gaussian_log_prior,
)
from server.learners.objective import MomentumAscent, maximize_lbfgs
from server.learners.settings import CompiledPlannerSteps, PlannerSettings

THETA_BOUND = 15.0


class ThetaFit:
    """The dynamics parameters theta of ``env``'s model space, fitted by momentum steps (the
    authors' schedule, compiled or in NumPy) or L-BFGS-B (``fits.DynamicsFit``)."""

    def __init__(self, env: Environment, settings: PlannerSettings) -> None:
        self.env = env
        self.settings = settings
        self.theta = env.model.initial_parameters()
        self.optimizer = MomentumAscent(
            env.model.num_parameters,
            settings.dynamics_learning_rate,
            settings.momentum,
            settings.max_step,
            clip=settings.momentum_clip,
        )

    @property
    def compiled(self) -> bool:
        """Whether ``steps`` and the teacher's gradient run compiled: the setting
        ``compiled_dynamics_steps`` (of the learners that have it), where the model space's
        primitives are one the kernels know."""
        settings = self.settings
        return (
            isinstance(settings, CompiledPlannerSteps)
            and bool(settings.compiled_dynamics_steps)
            and _primitive_family(self.env.model) is not None
        )

    def prior(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        """ln m(theta): the setting's Gaussian, else the model space's own prior (or none)."""
        sd = self.settings.dynamics_prior_sd
        if sd is None:
            sd = self.env.model.prior_sd
        if sd is None:
            return 0.0, np.zeros_like(theta)
        return gaussian_log_prior(theta, self.env.model.initial_value, sd)

    def gradient_rule(self, exact: bool) -> str:
        """The dynamics gradient of a momentum step ("authors" or "exact"); L-BFGS-B needs the
        exact one (``exact``)."""
        return "exact" if exact else str(self.settings.dynamics_gradient)

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
        prior, prior_grad = self.prior(theta)
        return value + prior, grad + prior_grad

    def pullback(
        self, teacher: TransitionModel, d_transitions: np.ndarray, exact: bool = True
    ) -> np.ndarray:
        """A gradient on ``teacher``'s table at theta, pulled back to theta (with
        ``exact=False``, by the setting's gradient rule)."""
        return teacher.pullback(self.theta, d_transitions, rule=self.gradient_rule(exact))

    def step(self, grad: np.ndarray) -> None:
        """One momentum step on theta, clipped where the model space clips it (the authors)."""
        theta = self.optimizer.step(self.theta, grad)
        bound = self.env.model.parameter_bound
        self.theta = theta if bound is None else np.clip(theta, -bound, bound)

    def steps(
        self,
        observed: ObservedTransitions,
        steps: int,
        teacher: TransitionModel | None = None,
        d_transitions: np.ndarray | None = None,
    ) -> float:
        """``steps`` momentum steps on theta for the observed transitions' likelihood and the
        dynamics prior, plus (BAM's step) the teacher data's gradient ``d_transitions`` on
        ``teacher``'s table pulled back to theta; by the setting's gradient rule. In one
        compiled call where ``compiled`` (``_kernels.theta_steps``), else step by step.
        Returns the likelihood plus prior at the last step's start (0 without steps)."""
        if steps <= 0:
            return 0.0
        if not self.compiled:
            value = 0.0
            for _ in range(steps):
                value, grad = self.transition_objective(self.theta, observed, exact=False)
                if teacher is not None and d_transitions is not None:
                    grad = grad + self.pullback(teacher, d_transitions, exact=False)
                self.step(grad)
            return value
        # A step's arithmetic is a few microseconds, which the NumPy calls of the likelihood,
        # the pull-back and the momentum step made about 50 (wall's BAM update: 140 steps).
        model = self.kernel_model(observed, teacher)
        if d_transitions is None:
            d_teacher = np.empty(0)
        else:
            flat = np.ascontiguousarray(d_transitions, dtype=np.float64).reshape(-1)
            d_teacher = flat[
                (self.env.model if teacher is None else teacher).flat_parametric_entries
            ]
        theta = np.array(self.theta, dtype=np.float64)  # copies: kept only if every step ends
        velocity = np.array(self.optimizer.velocity, dtype=np.float64)
        value, code, row = _kernels.theta_steps(theta, velocity, model, int(steps), d_teacher)
        self.raise_error(code, observed, row)
        self.theta, self.optimizer.velocity = theta, velocity
        return float(value)

    def kernel_model(
        self, observed: ObservedTransitions, teacher: TransitionModel | None
    ) -> tuple[Any, ...]:
        """What ``_kernels.theta_steps`` and ``_kernels.dynamics_steps`` read of the model space,
        the observed transitions, the teacher's table (``teacher``'s, else the environment's),
        the prior and the optimiser (``model``, as ``theta_steps`` describes it)."""
        model = self.env.model
        family = _primitive_family(model)
        assert family is not None
        authors = self.gradient_rule(exact=False) == "authors"
        taught_model = model if teacher is None else teacher
        sd = self.settings.dynamics_prior_sd
        if sd is None:
            sd = model.prior_sd
        if sd is not None and (not np.isfinite(sd) or sd <= 0):  # as gaussian_log_prior refuses it
            raise ValueError(f"prior standard deviation must be positive, got {sd!r}")
        bound = model.parameter_bound
        optimizer = self.optimizer
        moved, taught = model.moved_entries, taught_model.moved_entries
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
            authors and taught_model.outcomes is not None,
            model.initial_value,
            0.0 if sd is None else float(sd) ** 2,
            (
                optimizer.learning_rate, optimizer.momentum, optimizer.max_step,
                optimizer.clip == "step", np.inf if bound is None else float(bound),
            ),
        )  # fmt: skip

    def raise_error(self, code: int, observed: ObservedTransitions, row: int) -> None:
        """The error of a compiled step's ``code`` (0: none) at the observed ``row``."""
        if code == IMPOSSIBLE_TRANSITION:
            raise ValueError(
                f"observed transition {tuple(int(x) for x in observed.rows[row])} is "
                "impossible under the model space"
            )
        if code == GRADIENT_NOT_FINITE:
            raise FloatingPointError("the objective's gradient is not finite")

    def bounds(self) -> Bounds:
        """L-BFGS-B's box for the dynamics parameters: its line search may try points far
        out, where a logit saturates and an observed transition gets probability 0 (log -inf;
        seen in three-rooms and three-fields with feedback). Within +-15 every probability of
        the model space, and one minus it (a move that fails when a machine works with
        probability p), stays above 1e-13; the momentum schedule's clipped steps never get
        near."""
        return [(-THETA_BOUND, THETA_BOUND)] * self.env.model.num_parameters

    def fit_lbfgs(self, observed: ObservedTransitions, evaluations: int) -> tuple[float, int]:
        """Dynamics by L-BFGS-B on the observed transitions and the prior alone."""
        best, value, evaluations = maximize_lbfgs(
            lambda theta: self.transition_objective(theta, observed),
            self.theta.copy(),
            self.bounds(),
            evaluations,
        )
        self.theta = best
        return value, evaluations

    def stop_momentum(self) -> None:
        self.optimizer.velocity[:] = 0.0

    def state(self) -> dict[str, np.ndarray]:
        return {"theta": self.theta.copy(), "theta_velocity": self.optimizer.velocity.copy()}

    def load_state(self, state: dict[str, Any]) -> None:
        self.theta = self.env.model.check_parameters(state["theta"]).copy()
        self.optimizer.velocity = check_finite("theta velocity", state["theta_velocity"]).copy()


def _primitive_family(model: TransitionModel) -> tuple[int, int] | None:
    """The model space's primitives as ``_kernels.theta_steps`` takes them (the family and
    a softmax row's length), or None for a model space it does not know."""
    if type(model) is SigmoidModel:
        return _kernels.SIGMOID_PRIMITIVES, 1
    if type(model) is SoftmaxRowsModel:
        return _kernels.SOFTMAX_ROWS_PRIMITIVES, model.choices
    return None
