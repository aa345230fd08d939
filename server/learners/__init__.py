"""Learners: soft value iteration and its gradients, the A-SABL feedback model, BAM and its
baselines. Every learner is found through this registry: ``make("bam", env)``.

The registry is ``server.names.LEARNER_REGISTRY`` (its docstring states the order rule: append
only, a learner's position seeds its agents' random streams). ``LEARNERS`` imports each class
from its entry on first use, so importing this package loads no learner."""

from __future__ import annotations

from collections.abc import Mapping
from functools import cache
from importlib import import_module
from typing import TYPE_CHECKING, Any

from server.domains.base import Environment
from server.learners.base import Learner, UpdateResult, dumps, loads
from server.names import LEARNER_DISPLAY_NAMES, LEARNER_NAMES, LearnerInfo, RegistryMapping

if TYPE_CHECKING:
    from server.learners.bam import BAM  # at run time, ``__getattr__`` imports it on first use


@cache
def _load(entry: str) -> type[Learner]:
    module, _, attribute = entry.partition(":")
    cls = getattr(import_module(module), attribute)
    if not (isinstance(cls, type) and issubclass(cls, Learner)):
        raise TypeError(f"learner entry {entry!r} is not a Learner class")
    return cls


def _class_of(info: LearnerInfo) -> type[Learner]:
    cls = _load(info.entry)
    if cls.name != info.name:
        raise TypeError(f"learner {info.name!r}'s entry is the class of {cls.name!r}")
    return cls


# Learner name -> class, in the registry's order; each class imported on first use.
LEARNERS: Mapping[str, type[Learner]] = RegistryMapping(_class_of)
NAMES = LEARNER_NAMES
DISPLAY_NAMES = LEARNER_DISPLAY_NAMES


def learner_class(name: str) -> type[Learner]:
    try:
        return LEARNERS[name]
    except KeyError:
        raise ValueError(f"unknown learner {name!r}; valid: {', '.join(NAMES)}") from None


def make(name: str, env: Environment, seed: int = 0, **settings: Any) -> Learner:
    """A new learner of the given name for the environment; settings override the defaults."""
    return learner_class(name)(env, seed=seed, **settings)


def restore(env: Environment, state: dict[str, Any]) -> Learner:
    """A learner restored exactly from its ``state_dict()`` (or from ``loads(dumps(...))``)."""
    return learner_class(str(state.get("learner"))).from_state_dict(env, state)


def __getattr__(attribute: str) -> type[Learner]:
    if attribute == "BAM":
        return LEARNERS["bam"]
    raise AttributeError(f"module {__name__!r} has no attribute {attribute!r}")


__all__ = [
    "BAM",
    "DISPLAY_NAMES",
    "LEARNERS",
    "NAMES",
    "Learner",
    "UpdateResult",
    "dumps",
    "learner_class",
    "loads",
    "make",
    "restore",
]
