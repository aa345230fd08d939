"""The names the export uses for learners and environments, their display names and the order
in which the paper's tables list them."""

from __future__ import annotations

from collections.abc import Iterable, Mapping

from server.domains import title as environment_display
from server.names import LEARNER_DISPLAY_NAMES

# Learner name (as in the export) -> display name, in the order the tables list them after the
# baseline: the registry's (``server.names``), read at each use.
LEARNERS: Mapping[str, str] = LEARNER_DISPLAY_NAMES

# The four environments of the user study first, in the order of the paper's Table 1, then
# the other four (display names from ``server.domains.title``).
ENVIRONMENTS: tuple[str, ...] = (
    "two-rooms",
    "doorway",
    "two-fields",
    "three-fields",
    "wall",
    "three-rooms",
    "flip",
    "choices",
)

__all__ = ["ENVIRONMENTS", "LEARNERS", "environment_display", "learner_display"]


def learner_display(name: str) -> str:
    return LEARNERS[name]


def order_learners(names: Iterable[str], baseline: str) -> list[str]:
    """The baseline first, then the others in the order of ``LEARNERS``."""
    present = set(names)
    ordered = [baseline] if baseline in present else []
    ordered += [name for name in LEARNERS if name in present and name != baseline]
    return ordered


def order_environments(names: Iterable[str]) -> list[str]:
    """The paper's environments in the paper's order, then any others alphabetically."""
    present = set(names)
    known = [name for name in ENVIRONMENTS if name in present]
    return known + sorted(present - set(ENVIRONMENTS))


def threshold_label(threshold: float) -> str:
    """0.8 -> "80" (used in column names and, with a percent sign, in tables)."""
    return f"{round(threshold * 100, 6):g}"
