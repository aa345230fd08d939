"""Learners: soft value iteration and its gradients, the A-SABL feedback model, BAM and its
baselines. Every learner is found through this registry: ``make("bam", env)``."""

from __future__ import annotations

from typing import Any

from server.domains.base import Environment
from server.learners.bam import BAM
from server.learners.base import Learner, UpdateResult, dumps, loads
from server.learners.cloning import BehavioralCloning
from server.learners.global_cost import GlobalCostIRL
from server.learners.model_based import ModelBasedIRL
from server.names import LEARNER_DISPLAY_NAMES

LEARNERS: dict[str, type[Learner]] = {
    cls.name: cls for cls in (BAM, ModelBasedIRL, GlobalCostIRL, BehavioralCloning)
}
NAMES: tuple[str, ...] = tuple(LEARNERS)

DISPLAY_NAMES: dict[str, str] = LEARNER_DISPLAY_NAMES


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
