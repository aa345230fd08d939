"""What every table of the study file shares: unknown keys refused, values frozen; and the
colour, which the tutorial and the study's agents both have."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class Table(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Colour(Table):
    """An agent's colour: a name participants can read and the colour to draw."""

    name: str = Field(
        min_length=1, max_length=40, description="The colour's name, shown to participants."
    )
    hex: str = Field(pattern=r"^#[0-9A-Fa-f]{6}$", description="The colour drawn, as #RRGGBB.")
