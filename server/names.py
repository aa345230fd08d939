"""The learners' registry and the paper's names for them, kept apart from the learners' code so
that a command can name them without loading NumPy's and SciPy's learning stack
(``bam-study --help`` stays fast): this module imports nothing but the standard library.
Environments' names are ``server.domains.title``.

``LEARNER_REGISTRY`` is the one table of learners: each one's name (as in the study file, the
export and the settings tables), the paper's name for it, its colour and marker in the figures
and the entry point of its class. Every list of learners reads it, at each use:

- ``LEARNER_NAMES`` (``server.learners.NAMES``) and ``LEARNER_DISPLAY_NAMES``
  (``server.learners.DISPLAY_NAMES``, ``analysis.names.LEARNERS``);
- ``server.learners.LEARNERS``, the classes, each imported from its entry on first use;
- the figures of ``analysis.plots`` and ``server.simulation.plots``;
- the prose that lists the learners (``learner_names_prose``).

A new learner is its module and one ``LearnerInfo`` line here.

The order rule: **append only**. A learner's position in the registry seeds its simulated
agents' random streams (``server.simulation.protocols.agent_streams`` spawns them from entropy
that includes ``LEARNER_NAMES.index(name)``), so an entry inserted, removed or moved changes the
published curves of every learner after it. The order is also that of the paper's tables and of
the figures' legends.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import NamedTuple, TypeVar, overload

T = TypeVar("T")


class LearnerInfo(NamedTuple):
    """One learner of the registry.

    ``name``: the learner's name in the study file, the export and the settings tables (its
    class's ``name``); ``display``: the paper's name for it; ``colour`` and ``marker``: its
    lines and points in every figure (a colour-blind safe palette, matplotlib's marker codes);
    ``entry``: ``"module:Class"``, the class, imported on first use."""

    name: str
    display: str
    colour: str
    marker: str
    entry: str


def _by_name(*infos: LearnerInfo) -> dict[str, LearnerInfo]:
    table = {info.name: info for info in infos}
    if len(table) != len(infos):
        raise ValueError("a learner's name is registered twice")
    return table


# Append only: a learner's position seeds its agents' random streams (the module docstring).
LEARNER_REGISTRY: dict[str, LearnerInfo] = _by_name(
    LearnerInfo("bam", "BAM", "#0072B2", "o", "server.learners.bam:BAM"),
    LearnerInfo(
        "model-based",
        "Model-Based IRL",
        "#D55E00",
        "s",
        "server.learners.model_based:ModelBasedIRL",
    ),
    LearnerInfo(
        "global-cost",
        "Model-Based IRL (global cost)",
        "#009E73",
        "^",
        "server.learners.global_cost:GlobalCostIRL",
    ),
    LearnerInfo(
        "cloning", "Behavioral Cloning", "#CC79A7", "D", "server.learners.cloning:BehavioralCloning"
    ),
)


class _InRegistryOrder:
    """The registry's names in its order, read from it at each use."""

    def __len__(self) -> int:
        return len(LEARNER_REGISTRY)

    def __iter__(self) -> Iterator[str]:
        return iter(tuple(LEARNER_REGISTRY))


class _Names(_InRegistryOrder, Sequence[str]):
    @overload
    def __getitem__(self, index: int) -> str: ...

    @overload
    def __getitem__(self, index: slice) -> tuple[str, ...]: ...

    def __getitem__(self, index: int | slice) -> str | tuple[str, ...]:
        return tuple(LEARNER_REGISTRY)[index]

    def __repr__(self) -> str:
        return repr(tuple(LEARNER_REGISTRY))


class RegistryMapping(_InRegistryOrder, Mapping[str, T]):
    """Learner name -> ``value(its LearnerInfo)``, in the registry's order, read from it at
    each use."""

    def __init__(self, value: Callable[[LearnerInfo], T]) -> None:
        self._value = value

    def __getitem__(self, name: str) -> T:
        return self._value(LEARNER_REGISTRY[name])

    def __repr__(self) -> str:
        return repr(dict(self))


LEARNER_NAMES: Sequence[str] = _Names()
LEARNER_DISPLAY_NAMES: Mapping[str, str] = RegistryMapping(lambda info: info.display)


def learner_names_prose(display: bool = False) -> str:
    """The learners' names (or with ``display``, the paper's names) as a sentence lists them:
    "bam, model-based, global-cost, cloning"."""
    return ", ".join(info.display if display else info.name for info in LEARNER_REGISTRY.values())
