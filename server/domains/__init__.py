"""The grid-world domains of the paper: the registry is the one way to get an environment.

    >>> from server import domains
    >>> env = domains.make("doorway")
    >>> env.num_states, env.horizon, env.task_names
    (121, 44, ('A', 'B', 'C', 'D'))

Eight environments are used in the simulations and the user study (``ENVIRONMENTS``); three
tutorials teach participants the interface (``TUTORIALS``). Layouts are the text maps in
``maps/``; the domains' rules are in ``navigation.py``, ``gravity.py`` and ``farming.py``; the
keys of ``Environment.layout`` (walls, terrain, machines, colours, gravity_of_colour) are
described in ``grid.py``. ``make`` returns a shared, cached instance whose arrays are
read-only.

A study may define environments of its own (``spec.EnvironmentSpec``, from the study file's
``[environments.NAME]`` tables): ``register`` checks and builds one, after which ``make``,
``domain_of`` and ``names`` know it as they know the built-in ones. A process that serves or
simulates a study registers its environments once; processes it spawns get them through
``register_all(registered())``.
"""

from __future__ import annotations

from functools import cache
from types import ModuleType

import numpy as np

from server.domains import farming, gravity, navigation
from server.domains.base import Environment
from server.domains.grid import load_map
from server.domains.spec import DEFAULT_MAX_STATES, EnvironmentSpec

DOMAINS: dict[str, tuple[str, ...]] = {
    "navigation": ("wall", "doorway", "two-rooms", "three-rooms"),
    "gravity": ("flip", "choices"),
    "farming": ("two-fields", "three-fields"),
}
TUTORIALS: dict[str, str] = {
    "navigation": "navigation-tutorial",
    "gravity": "gravity-tutorial",
    "farming": "farming-tutorial",
}
ENVIRONMENTS: tuple[str, ...] = tuple(name for names in DOMAINS.values() for name in names)


def title(name: str) -> str:
    """An environment's display name, in the paper's words: 'two-rooms' -> 'Two Rooms' (every
    name is its words capitalised, so an environment the paper does not know gets one too)."""
    return " ".join(word.capitalize() for word in name.replace("_", "-").split("-") if word)


NAMES: tuple[str, ...] = (
    *ENVIRONMENTS,
    "navigation-tutorial",
    "farming-tutorial",
    "gravity-tutorial",
)

_MODULES: dict[str, ModuleType] = {
    "navigation": navigation,
    "gravity": gravity,
    "farming": farming,
}
# The gravity tutorial is the flip layout.
_MAP_OF: dict[str, str] = {"gravity-tutorial": "flip"}
# The environments studies defined, by name: their definitions and the built environments.
_DEFINED: dict[str, tuple[EnvironmentSpec, Environment]] = {}


def names() -> tuple[str, ...]:
    """Every environment ``make`` knows: the built-in ones, then those registered."""
    return (*NAMES, *_DEFINED)


def _unknown(name: object) -> ValueError:
    return ValueError(f"unknown environment {name!r}; valid names: {', '.join(names())}")


def domain_of(name: str) -> str:
    """The domain (navigation, gravity or farming) of a registered environment."""
    for domain, listed in DOMAINS.items():
        if name in listed or TUTORIALS[domain] == name:
            return domain
    if name in _DEFINED:
        return _DEFINED[name][1].domain
    raise _unknown(name)


def make(name: str) -> Environment:
    """The environment registered under ``name`` (shared and cached: treat it as read-only)."""
    if isinstance(name, str) and name in _DEFINED:
        return _DEFINED[name][1]
    if not isinstance(name, str) or name not in NAMES:
        raise _unknown(name)
    return _make(name)


def register(spec: EnvironmentSpec, max_states: int = DEFAULT_MAX_STATES) -> Environment:
    """Check and build a study's environment and make it known by its name (``MapProblems``
    lists every problem). Registering the same definition again is harmless; another
    definition under a name already known is an error."""
    if spec.name in NAMES:
        raise ValueError(f"environment {spec.name!r} is built in: give yours another name")
    known = _DEFINED.get(spec.name)
    if known is not None:
        if known[0] != spec:
            raise ValueError(f"environment {spec.name!r} is already defined differently")
        return known[1]
    environment = spec.build(max_states)
    _DEFINED[spec.name] = (spec, environment)
    return environment


def register_all(specs: tuple[EnvironmentSpec, ...]) -> None:
    """Register each definition (a spawned process's initialiser: ``registered()``)."""
    for spec in specs:
        register(spec, max_states=2**62)  # checked against the study's limit already


def registered() -> tuple[EnvironmentSpec, ...]:
    """The definitions registered in this process, in order."""
    return tuple(spec for spec, _ in _DEFINED.values())


def definition(name: str) -> EnvironmentSpec | None:
    """The definition of a registered study environment (for a process that has not registered
    it: a Dask worker); None for a built-in one."""
    known = _DEFINED.get(name)
    return None if known is None else known[0]


def unregister(name: str) -> None:
    """Forget a registered environment (a study's environments, when it stops)."""
    if name not in _DEFINED:
        raise _unknown(name)
    del _DEFINED[name]


@cache
def _make(name: str) -> Environment:
    module = _MODULES[domain_of(name)]
    return module.build(name, load_map(_MAP_OF.get(name, name)))


def true_model_parameters(env: Environment) -> np.ndarray:
    """Dynamics parameters under which ``env.model`` reproduces ``env``'s true dynamics."""
    if env.domain not in _MODULES:
        raise ValueError(f"unknown domain {env.domain!r}")
    result: np.ndarray = _MODULES[env.domain].true_model_parameters(env)
    return result


__all__ = [
    "DOMAINS",
    "ENVIRONMENTS",
    "NAMES",
    "TUTORIALS",
    "EnvironmentSpec",
    "domain_of",
    "make",
    "names",
    "register",
    "register_all",
    "registered",
    "true_model_parameters",
    "unregister",
]
