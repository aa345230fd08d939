"""The learners' settings: frozen dataclasses whose every field has a type, a default and a
description, checked where they are made.

A learner's ``settings_type`` is one of them (``CommonSettings`` for every learner,
``PlannerSettings`` for the learners that plan, each learner's own beside its class:
``BAMSettings`` in ``bam.py`` and so on), and ``learner.settings`` is an instance, read as
attributes (``learner.settings.beta``). A value of the wrong type or outside its choices is a
``ValueError`` naming the setting as it is made: by ``make``, by a restored state, by the
study file's ``[learner_settings.NAME]`` (``Settings.of`` also names the valid keys of a key
that is not one). The docs' table of learner settings (``scripts/docs_hooks.py``) is generated
from ``Settings.described``.

A field is declared with ``setting(default, description, ...)``; a learner whose default
differs redeclares it with ``setting_of(Base, name, default)``, which keeps the base's
description and check. This module imports nothing but the standard library and
``server.domains.base``: ``server.learners.base`` reads it on import.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from numbers import Integral, Real
from typing import Any, NamedTuple, Self

from server.domains.base import GRADIENT_RULES

# A field's own check, called with its name and value: raises ValueError.
Check = Callable[[str, Any], None]

OPTIMIZERS = ("momentum", "lbfgs", "warm-lbfgs")
# One optimiser per task's parameters (the authors'), or one for all of them.
OPTIMIZER_SCOPES = ("per-task", "joint")
MOMENTUM_CLIPS = ("step", "velocity")
COST_CELLS = ("domain", "every")
# The keys of ``planning.PRECISIONS`` (a test holds them equal; that module loads numba).
PLANNER_PRECISIONS = ("float64", "float32")


def check_choice(name: str, value: Any, choices: tuple[str, ...]) -> None:
    """A setting that must be one of ``choices``."""
    if value not in choices:
        raise ValueError(f"{name} must be one of {', '.join(map(repr, choices))}, got {value!r}")


def check_positive_or_none(name: str, value: Any) -> None:
    """A setting that is a positive number, or None (bools are refused)."""
    if value is not None and (not _is_number(value) or value <= 0):
        raise ValueError(f"{name} must be a positive number or None, got {value!r}")


def check_count(name: str, value: Any, minimum: int) -> None:
    """A whole-number setting of at least ``minimum`` (0 or 1); bools are refused."""
    if not _is_integer(value) or value < minimum:
        kind = "positive" if minimum == 1 else "non-negative"
        raise ValueError(f"{name} must be a {kind} integer, got {value!r}")


def check_positive_count(name: str, value: Any) -> None:
    check_count(name, value, minimum=1)


def check_non_negative_count(name: str, value: Any) -> None:
    check_count(name, value, minimum=0)


def check_share(name: str, value: Any) -> None:
    """A setting that is a number in (0, 1]; bools are refused."""
    if not _is_number(value) or not 0 < value <= 1:
        raise ValueError(f"{name} must be a number greater than 0 and at most 1, got {value!r}")


def _is_integer(value: Any) -> bool:
    return isinstance(value, Integral) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return isinstance(value, Real) and not isinstance(value, bool)


class Kind(NamedTuple):
    """What values a field's annotation admits, in words, and the test of one."""

    words: str
    admits: Callable[[Any], bool]


# A field's annotation (a string: the modules use ``from __future__ import annotations``).
KINDS: dict[str, Kind] = {
    "float": Kind("a number", _is_number),
    "int": Kind("an integer", _is_integer),
    "bool": Kind("true or false", lambda value: isinstance(value, bool)),
    "str": Kind("a string", lambda value: isinstance(value, str)),
    "float | None": Kind("a number or unset", lambda value: value is None or _is_number(value)),
}


def setting(
    default: Any = dataclasses.MISSING,
    description: str = "",
    *,
    choices: tuple[str, ...] = (),
    check: Check | None = None,
) -> Any:
    """A field of a ``Settings`` class: its default (none: each learner's class gives it), what
    it does (``description``, shown in the docs), the strings it may be (``choices``) and a
    check of its own (``check``, in place of the check of its annotated type)."""
    if not description:
        raise ValueError("a learner setting needs a description")
    metadata = {"description": description, "choices": choices, "check": check}
    return dataclasses.field(default=default, metadata=metadata)


def setting_of(
    owner: type[Settings], name: str, default: Any, description: str | None = None
) -> Any:
    """``owner``'s field ``name`` with another default (and, given, another description), for
    a learner whose default differs; its choices and check kept."""
    base = owner.field(name)
    metadata = dict(base.metadata)
    if description is not None:
        metadata["description"] = description
    return dataclasses.field(default=default, metadata=metadata)


class SettingInfo(NamedTuple):
    """One field of a ``Settings`` class as the docs show it."""

    name: str
    kind: str  # the values it admits, in words
    default: Any  # dataclasses.MISSING: none
    description: str


@dataclass(frozen=True, kw_only=True)
class Settings:
    """A learner's settings; this class itself: a learner without settings."""

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            check: Check | None = field.metadata.get("check")
            choices: tuple[str, ...] = field.metadata.get("choices", ())
            if check is not None:
                check(field.name, value)
            elif choices:
                check_choice(field.name, value, choices)
            else:
                kind = _kind(field)
                if not kind.admits(value):
                    raise ValueError(f"{field.name} must be {kind.words}, got {value!r}")

    @classmethod
    def names(cls) -> tuple[str, ...]:
        return tuple(field.name for field in dataclasses.fields(cls))

    @classmethod
    def field(cls, name: str) -> dataclasses.Field[Any]:
        for field in dataclasses.fields(cls):
            if field.name == name:
                return field
        raise KeyError(f"{cls.__name__} has no setting {name!r}")

    @classmethod
    def defaults(cls) -> dict[str, Any]:
        """Every setting's default, by name (the ``default_settings`` of a learner)."""
        return {
            field.name: field.default
            for field in dataclasses.fields(cls)
            if field.default is not dataclasses.MISSING
        }

    @classmethod
    def of(cls, overrides: Mapping[str, Any]) -> Self:
        """The defaults with ``overrides``; a key that is not a setting is an error that lists
        the valid ones, as is a value that its setting refuses."""
        names = cls.names()
        unknown = sorted(set(overrides) - set(names))
        if unknown:
            raise ValueError(
                f"unknown setting(s) {', '.join(unknown)}; valid: {', '.join(sorted(names))}"
            )
        return cls(**overrides)

    @classmethod
    def described(cls) -> list[SettingInfo]:
        """Each setting's name, the values it admits, its default and what it does."""
        infos = []
        for field in dataclasses.fields(cls):
            choices = field.metadata.get("choices", ())
            words = _kind(field).words.removeprefix("a ").removeprefix("an ")
            kind = " or ".join(f'"{c}"' for c in choices) if choices else words
            infos.append(
                SettingInfo(field.name, kind, field.default, field.metadata["description"])
            )
        return infos

    def as_dict(self) -> dict[str, Any]:
        """Every setting by name, as a learner's saved state stores them."""
        return {field.name: getattr(self, field.name) for field in dataclasses.fields(self)}

    def replace(self, **changes: Any) -> Self:
        """These settings with ``changes``, checked again."""
        return dataclasses.replace(self, **changes)


@functools.cache
def _kind_of(annotation: str) -> Kind:
    if annotation not in KINDS:
        raise TypeError(f"a learner setting's type must be one of {', '.join(KINDS)}")
    return KINDS[annotation]


def _kind(field: dataclasses.Field[Any]) -> Kind:
    annotation = field.type if isinstance(field.type, str) else field.type.__name__
    return _kind_of(annotation)


@dataclass(frozen=True, kw_only=True)
class CommonSettings(Settings):
    """Settings every learner shares: the teacher's action and feedback models and the
    momentum ascent (the paper's authors' reference settings)."""

    beta: float = setting(
        1.0,
        "The teacher's inverse temperature: the action model's p(a|s) is proportional to "
        "exp(beta Q(s, a)), and the soft planner's values are computed at it.",
    )
    normalized_actions: bool = setting(
        True,
        "true: the authors' normalised action model, exp(beta (Q(s, a) - Q(s, STAY)) / "
        "std_a Q(s, .)), which stays meaningful as Q grows with the horizon; false: the "
        "paper's plain exp(beta Q(s, a)).",
    )
    variance_floor: float = setting(
        0.0,
        "Added to the variance of a Q row in the normalised action model (0: the authors' "
        "rule, which divides by 1 where all of a row's values are equal).",
    )
    epsilon: float = setting(
        0.05,
        "A-SABL's error rate (equations (3)-(4)): the chance the teacher's feedback says the "
        "opposite of what the advantage would, in [0, 0.5).",
    )
    alpha: float = setting(
        1.0, "A-SABL's slope: feedback follows sigmoid(alpha x advantage) (equations (3)-(4))."
    )
    mu_plus: float = setting(
        0.1, "A-SABL's mu+: the chance the teacher gives no feedback where it would be +."
    )
    mu_minus: float = setting(
        0.1, "A-SABL's mu-: the chance the teacher gives no feedback where it would be -."
    )
    momentum: float = setting(
        0.7, "The momentum ascent's momentum: velocity = momentum x velocity + rate x gradient."
    )
    max_step: float = setting(
        0.1, "The largest norm of a momentum step (of each optimiser's parameters)."
    )
    momentum_clip: str = setting(
        "step",
        '"step": the authors\' clipped momentum (the velocity unclipped, the applied step '
        'clipped); "velocity": the clipped step kept as the velocity.',
        choices=MOMENTUM_CLIPS,
    )


@dataclass(frozen=True, kw_only=True)
class PlannerSettings(CommonSettings):
    """Settings of the learners that fit a dynamics model and per-cell costs through the soft
    planner (BAM, model-based IRL, global cost): the priors, the optimisers and the planner's
    passes. ``cost_steps`` and ``dynamics_steps`` have each learner's own defaults."""

    cost_prior_sd: float = setting(
        1.0, "The deviation of the costs' Gaussian prior N(0, sd), centred on 0."
    )
    cost_bound: float = setting(3.0, "The costs are clipped to +-this after every step.")
    cost_learning_rate: float = setting(0.01, "The learning rate of the momentum cost steps.")
    dynamics_learning_rate: float = setting(
        1.0, "The learning rate of the momentum steps on the dynamics parameters theta."
    )
    dynamics_prior_sd: float | None = setting(
        None,
        "m(theta): unset is the model space's own prior, the authors' (navigation and "
        "farming: none; gravity: N(0, 1)); a number is a Gaussian prior of that deviation "
        "centred on the model's initialisation.",
        check=check_positive_or_none,
    )
    cost_optimizers: str = setting(
        "per-task",
        '"per-task": each task\'s costs have an optimiser of their own, whose step is clipped '
        "on its own (the authors'); \"joint\": one optimiser over every task's costs.",
        choices=OPTIMIZER_SCOPES,
    )
    cost_cells: str = setting(
        "domain",
        '"domain": the cells the environment\'s model space gives a cost (farming: the '
        "fields, not the dirt, as the authors' learners have it; elsewhere every cell); "
        '"every": all.',
        choices=COST_CELLS,
    )
    dynamics_gradient: str = setting(
        "authors",
        '"authors": the dynamics gradient of the authors\' model space where it is not the '
        'exact gradient of the likelihood (farming); "exact": the gradient of equation (5). '
        "L-BFGS-B always uses the exact gradient.",
        choices=GRADIENT_RULES,
    )
    optimizer: str = setting(
        "momentum",
        '"momentum": the reference schedule of fixed momentum steps on every update; '
        '"lbfgs": L-BFGS-B over the parameter blocks on every update, stopping at '
        'convergence or after max_evaluations evaluations; "warm-lbfgs": the momentum '
        "schedule for a task's first fit, L-BFGS-B from the warm start later, capped at "
        'warm_evaluations (docs/defaults.md, "A faster optimiser").',
        choices=OPTIMIZERS,
    )
    planner_precision: str = setting(
        "float32",
        '"float32": the planner\'s passes in single precision, Q and the gradients to about '
        "1e-5 relative, the agents as the float64 passes' (docs/defaults.md, \"Float32 "
        'passes"), an update 0-33% cheaper; "float64": double precision, as the published '
        "reproduction runs were made.",
        choices=PLANNER_PRECISIONS,
    )
    max_evaluations: int = setting(
        40,
        'With optimizer "lbfgs": the most objective evaluations of an update\'s L-BFGS-B.',
        check=check_positive_count,
    )
    warm_evaluations: int = setting(
        20,
        'With optimizer "warm-lbfgs": the most objective evaluations of a warm update\'s L-BFGS-B.',
        check=check_positive_count,
    )
    warm_share: float = setting(
        1.0,
        'With optimizer "momentum": the share of the planning steps an update runs when every '
        "task it plans was fitted before (a warm start), at least one; 1 is the authors' "
        "schedule on every update. A task's first fit runs the whole schedule "
        '(docs/defaults.md, "Shorter warm updates").',
        check=check_share,
    )
    cost_steps: int = setting(description="Momentum steps on the costs (each learner's own).")
    dynamics_steps: int = setting(
        description="Momentum steps on the dynamics parameters (each learner's own)."
    )


@dataclass(frozen=True, kw_only=True)
class CompiledPlannerSteps(Settings):
    """The compiled momentum steps of BAM and model-based IRL (global cost has none: its
    global cost ties the tasks' steps together, and its runs are its published ones')."""

    compiled_steps: bool = setting(
        True,
        "true: an update's momentum cost steps, each task's (with per-task optimisers), in "
        "one compiled call, the agents as the NumPy steps' (docs/defaults.md, \"Compiled cost "
        'steps"), not to the last bit; false: step by step in NumPy, as the published '
        "reproduction runs were made.",
    )
    compiled_dynamics_steps: bool = setting(
        True,
        "true: an update's momentum steps on the dynamics parameters (BAM's outside their "
        "planner passes; model-based IRL's whole dynamics fit) in compiled calls, the agents "
        'as the NumPy steps\' (docs/defaults.md, "Compiled dynamics steps"), not to the last '
        "bit; false: in NumPy, as the runs before them were made.",
    )
