"""What a learner observes, as typed records checked once where they are made.

The study server, the simulated teacher and library users hand a learner these records
(``Learner.observe``); the learner keeps them in its integer tables (``base.DataLog``).

- ``DemonstrationStep``: a teacher's action for a task and the transition it made.
- ``AgentStep``: the agent's own action, the transition it made and the feedback on it (0: none).
- ``IdleMove``: a move without a demonstration (the study's idle mode; ``transition`` in the
  events' ``record`` column): a transition alone, which tells the learner about dynamics only.
- ``Feedback``: +1 or -1 on the most recent agent step (the study's +/- keys).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from numbers import Integral


def _check_indices(record: object) -> None:
    """Every field a whole number (NumPy's included, stored as ``int``); indices not negative."""
    for field in fields(record):  # type: ignore[arg-type]
        value = getattr(record, field.name)
        if isinstance(value, bool) or not isinstance(value, Integral):
            raise ValueError(
                f"{type(record).__name__}.{field.name} must be an integer, got {value!r}"
            )
        if field.name != "feedback" and value < 0:
            raise ValueError(
                f"{type(record).__name__}.{field.name} must not be negative, got {value!r}"
            )
        object.__setattr__(record, field.name, int(value))


@dataclass(frozen=True)
class DemonstrationStep:
    task: int
    state: int
    action: int
    next_state: int

    def __post_init__(self) -> None:
        _check_indices(self)


@dataclass(frozen=True)
class AgentStep:
    task: int
    state: int
    action: int
    next_state: int
    feedback: int = 0  # +1, -1, or 0 for none

    def __post_init__(self) -> None:
        _check_indices(self)
        if self.feedback not in (-1, 0, 1):
            raise ValueError(f"feedback must be +1, -1 or 0 (none), got {self.feedback!r}")


@dataclass(frozen=True)
class IdleMove:
    state: int
    action: int
    next_state: int

    def __post_init__(self) -> None:
        _check_indices(self)


@dataclass(frozen=True)
class Feedback:
    feedback: int  # +1 or -1

    def __post_init__(self) -> None:
        _check_indices(self)
        if self.feedback not in (-1, 1):
            raise ValueError(f"feedback must be +1 or -1, got {self.feedback!r}")


Observation = DemonstrationStep | AgentStep | IdleMove | Feedback
