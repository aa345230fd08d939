"""The grid-world domains of the paper: the registry is the one way to get an environment.

    >>> from server import domains
    >>> env = domains.make("doorway")
    >>> env.num_states, env.horizon, env.task_names
    (121, 44, ('A', 'B', 'C', 'D'))

Eight environments are used in the simulations and the user study (``ENVIRONMENTS``); three
tutorials teach participants the interface (``TUTORIALS``). Layouts are the text maps in
``maps/``; the families' rules are in ``navigation.py``, ``gravity.py`` and ``farming.py``; the
keys of ``Environment.layout`` (walls, terrain, machines, colours, gravity_of_colour) are
described in ``grid.py``. ``make`` returns a shared, cached instance whose arrays are
read-only.
"""

from __future__ import annotations

from functools import cache
from types import ModuleType

import numpy as np

from server.domains import farming, gravity, navigation
from server.domains.base import Environment
from server.domains.grid import load_map

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

_FAMILIES: dict[str, ModuleType] = {
    "navigation": navigation,
    "gravity": gravity,
    "farming": farming,
}
# The gravity tutorial is the flip layout.
_MAP_OF: dict[str, str] = {"gravity-tutorial": "flip"}


def domain_of(name: str) -> str:
    """The domain (navigation, gravity or farming) of a registered environment."""
    for domain, names in DOMAINS.items():
        if name in names or TUTORIALS[domain] == name:
            return domain
    raise ValueError(f"unknown environment {name!r}; valid names: {', '.join(NAMES)}")


def make(name: str) -> Environment:
    """The environment registered under ``name`` (shared and cached: treat it as read-only)."""
    if not isinstance(name, str) or name not in NAMES:
        raise ValueError(f"unknown environment {name!r}; valid names: {', '.join(NAMES)}")
    return _make(name)


@cache
def _make(name: str) -> Environment:
    family = _FAMILIES[domain_of(name)]
    return family.build(name, load_map(_MAP_OF.get(name, name)))


def true_model_parameters(env: Environment) -> np.ndarray:
    """Dynamics parameters under which ``env.model`` reproduces ``env``'s true dynamics."""
    if env.domain not in _FAMILIES:
        raise ValueError(f"unknown domain {env.domain!r}")
    result: np.ndarray = _FAMILIES[env.domain].true_model_parameters(env)
    return result


__all__ = [
    "DOMAINS",
    "ENVIRONMENTS",
    "NAMES",
    "TUTORIALS",
    "domain_of",
    "make",
    "true_model_parameters",
]
