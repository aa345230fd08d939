"""The names the export uses for learners and environments, their display names and the order
in which the paper's tables list them."""

from __future__ import annotations

from collections.abc import Iterable

# Learner name (as in the export) -> display name, in the order the tables list them after
# the baseline.
LEARNERS: dict[str, str] = {
    "bam": "BAM",
    "model-based": "Model-Based IRL",
    "global-cost": "Model-Based IRL (global cost)",
    "cloning": "Behavioral Cloning",
}

# Environment name -> display name: the four environments of the user study first, in the
# order of the paper's Table 1, then the other four.
ENVIRONMENTS: dict[str, str] = {
    "two-rooms": "Two Rooms",
    "doorway": "Doorway",
    "two-fields": "Two Fields",
    "three-fields": "Three Fields",
    "wall": "Wall",
    "three-rooms": "Three Rooms",
    "flip": "Flip",
    "choices": "Choices",
}


def learner_display(name: str) -> str:
    return LEARNERS[name]


def environment_display(name: str) -> str:
    """The paper's name for an environment; an environment the paper does not know is shown
    with its words capitalised ("my-maze" -> "My Maze")."""
    if name in ENVIRONMENTS:
        return ENVIRONMENTS[name]
    return " ".join(word.capitalize() for word in name.replace("_", "-").split("-") if word)


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
