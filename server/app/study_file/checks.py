"""The checks a participant passes through: the device check before consent
(``[device_check]``) and the instructional attention checks between agents
(``[attention_checks]``)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field, field_validator, model_validator

from server.app.study_file.base import Table

Cell = tuple[int, int]


class AttentionChecks(Table):
    """Instructional attention checks between agents: a small open grid, a robot and a star;
    the participant is asked to move the robot to the star with the arrow keys, and passes on
    reaching it within the moves allowed (Prolific accepts failed instructional attention checks
    as a ground for rejection)."""

    enabled: bool = Field(False, strict=True, description="Show attention checks between agents.")
    size: int = Field(
        5,
        ge=3,
        le=9,
        strict=True,
        description="The grid's width and height, in cells (an open square grid).",
    )
    start: Cell | Literal["random"] = Field(
        (4, 0),
        description="Where the robot starts, as [row, column] from the top-left cell [0, 0], "
        'or "random": drawn for each check from the participant\'s seed.',
    )
    star: Cell | Literal["random"] = Field(
        (0, 4),
        description='Where the star is, as [row, column], or "random": drawn for each check '
        "from the participant's seed, at least size - 1 moves from the robot.",
    )
    moves: int = Field(
        12,
        ge=1,
        le=100,
        strict=True,
        description="The moves allowed to reach the star (a move into the edge counts): at "
        "least the shortest way, and with a random start or star at least 2 x (size - 1).",
    )
    every: int = Field(
        1,
        ge=1,
        le=100,
        strict=True,
        description="A check after every k-th agent (1: after each agent), never after the "
        "last agent.",
    )

    @field_validator("start", "star", mode="before")
    @classmethod
    def _cell(cls, value: Any) -> Any:
        if value == "random":
            return value
        whole = [x for x in value if type(x) is int] if isinstance(value, list | tuple) else []
        if len(whole) != 2 or len(value) != 2:
            raise ValueError('a cell is [row, column], two whole numbers, or "random"')
        return value

    @model_validator(mode="after")
    def _reachable(self) -> AttentionChecks:
        for name, cell in (("start", self.start), ("star", self.star)):
            if cell != "random" and not all(0 <= x < self.size for x in cell):
                raise ValueError(
                    f"{name} {list(cell)} is off the {self.size}x{self.size} grid "
                    f"(rows and columns 0 to {self.size - 1})"
                )
        if self.start == "random" or self.star == "random":
            least = 2 * (self.size - 1)
        else:
            if self.start == self.star:
                raise ValueError("start and star are the same cell")
            least = abs(self.start[0] - self.star[0]) + abs(self.start[1] - self.star[1])
        if self.moves < least:
            raise ValueError(
                f"moves ({self.moves}) is less than the {least} the star may need at the least"
            )
        return self

    def after_agents(self, agents: int) -> list[int]:
        """The agents' positions (from 0) after which a check comes, of ``agents`` agents."""
        if not self.enabled:
            return []
        return [p for p in range(agents - 1) if (p + 1) % self.every == 0]


class DeviceCheck(Table):
    """The check of the participant's device before consent: one arrow key pressed (the
    teaching page is driven by the arrow keys), a window large enough for the teaching page,
    and a browser with what the page uses. A participant whose device fails is turned away
    (status incompatible), on Prolific with the study's INCOMPATIBLE_DEVICE code."""

    enabled: bool = Field(False, description="Check the device before the consent page.")
    min_width: int = Field(
        1000, ge=320, le=4000, description="The narrowest window taken, in CSS pixels."
    )
    min_height: int = Field(
        600, ge=320, le=4000, description="The lowest window taken, in CSS pixels."
    )
    key_seconds: float = Field(
        60,
        ge=1,
        le=600,
        description="How long the page waits for an arrow key press before it turns the "
        "participant away (a device without arrow keys: a phone, a tablet).",
    )
