"""Learners: soft value iteration and its gradients, the A-SABL feedback model, BAM and its
baselines. Every learner is found through this registry: ``make("bam", env)``.

The registry is ``server.names.LEARNER_REGISTRY`` (its docstring states the order rule: append
only, a learner's position seeds its agents' random streams). ``LEARNERS`` imports each class
from its entry on first use, so importing this package loads no learner."""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from functools import cache
from importlib import import_module
from typing import TYPE_CHECKING, Any

from server.domains.base import Environment
from server.learners.base import Learner, UpdateResult, dumps, loads
from server.names import LEARNER_DISPLAY_NAMES, LEARNER_NAMES, LEARNER_REGISTRY

if TYPE_CHECKING:
    from server.learners.bam import BAM  # at run time, ``__getattr__`` imports it on first use


@cache
def _load(entry: str) -> type[Learner]:
    module, _, attribute = entry.partition(":")
    cls = getattr(import_module(module), attribute)
    if not (isinstance(cls, type) and issubclass(cls, Learner)):
        raise TypeError(f"learner entry {entry!r} is not a Learner class")
    return cls


class _Classes(Mapping[str, type[Learner]]):
    """Learner name -> class, in the registry's order; each class imported on first use."""

    def __getitem__(self, name: str) -> type[Learner]:
        cls = _load(LEARNER_REGISTRY[name].entry)
        if cls.name != name:
            raise TypeError(f"learner {name!r}'s entry is the class of {cls.name!r}")
        return cls

    def __len__(self) -> int:
        return len(LEARNER_REGISTRY)

    def __iter__(self) -> Iterator[str]:
        return iter(tuple(LEARNER_REGISTRY))

    def __repr__(self) -> str:
        return repr({name: info.entry for name, info in LEARNER_REGISTRY.items()})


LEARNERS: Mapping[str, type[Learner]] = _Classes()
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
