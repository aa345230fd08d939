"""The study's own environments (``[environments.NAME]``) and its domains (``[[domains]]``).

An environment's keys are ``EnvironmentSpec``'s fields (``server.domains.spec``), their types
and defaults: the table's model is made from that dataclass, so that the two cannot drift
apart. What the study file adds is here: each key's description (the docs' table) and the
bounds of its value (``KEYS``), ``map_file``, the map read from a file, and ``family``, the
former name of ``domain``, still accepted for the study files written with it.
"""

from __future__ import annotations

import dataclasses
import typing
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from pydantic import Field, ValidationInfo, create_model, model_validator

from server.app.study_file.base import Table
from server.domains.spec import DEFAULT_MAX_STATES, DOMAIN_NAMES, EnvironmentSpec

# Each of EnvironmentSpec's fields but its name (the table's own name): its description and
# the bounds the study file sets on its value.
KEYS: dict[str, dict[str, Any]] = {
    "domain": {
        "description": "The environment's domain: navigation, gravity or farming (formerly "
        "family, which is still accepted)."
    },
    "map": {
        "description": "The map's text: header lines (task:, start:, gravity of ...:), the "
        "column digits, then one numbered line per row."
    },
    "horizon": {
        "ge": 1,
        "le": 1000,
        "description": "Steps per task; unset: the domain's own (navigation 2 x (width + "
        "height), gravity and farming 4 x (width + height)).",
    },
    "colours": {
        "description": "The colour drawn for each new terrain, machine or gravity colour, e.g. "
        '{ vines = "#6b8e23" }.'
    },
    "gravity_colours": {
        "description": "Gravity only: colours beyond orange (o), green (g) and purple (p), "
        'each a lower-case letter and its name, e.g. { y = "yellow" }.'
    },
    "gravity": {
        "description": "Gravity only: the gravity each colour sets (north, south, east or "
        "west); the map's 'gravity of COLOUR:' lines may give it instead."
    },
    "terrains": {
        "description": "Farming only: field terrains beyond soil (s), grass (i) and crops (c), "
        'each a lower-case letter and its name, e.g. { v = "vines" }.'
    },
    "machines": {
        "description": "Farming only: machines beyond the plow (P), sprinkler (W) and "
        'harvester (H), each a capital letter and its name, e.g. { T = "trellis" }.'
    },
    "works_on": {
        "description": "Farming only: the terrain each machine enters (required for a new "
        'machine; the others keep theirs unless given), e.g. { trellis = "vines" }.'
    },
    "max_trapped_start_share": {
        "ge": 0,
        "le": 1,
        "description": "The share of a task's start probability (the simulations' or the user "
        "study's) that may lie on starts from which its goal can never be reached, whatever "
        "the agent does; 0: none (bam-study check names them).",
    },
}
MAP_FILE = Field(
    None,
    description="Instead of map: a file holding the map, its path relative to the study file.",
)


def _table_fields() -> dict[str, Any]:
    """The keys of an ``[environments.NAME]`` table: ``EnvironmentSpec``'s fields but its name,
    in its order, with their types and defaults and ``KEYS``' descriptions and bounds; the
    domain one of ``DOMAIN_NAMES``, and the map optional, as ``map_file`` may stand for it."""
    spec_fields = [f for f in dataclasses.fields(EnvironmentSpec) if f.name != "name"]
    if [f.name for f in spec_fields] != list(KEYS):
        raise TypeError(
            f"KEYS ({', '.join(KEYS)}) must describe EnvironmentSpec's fields, in their order: "
            f"{', '.join(f.name for f in spec_fields)}"
        )
    hints = typing.get_type_hints(EnvironmentSpec)
    fields: dict[str, Any] = {}
    for spec_field in spec_fields:
        annotation: Any = hints[spec_field.name]
        options = dict(KEYS[spec_field.name])
        if spec_field.default_factory is not dataclasses.MISSING:
            options["default_factory"] = spec_field.default_factory
        elif spec_field.default is not dataclasses.MISSING:
            options["default"] = spec_field.default
        if spec_field.name == "domain":
            annotation = Literal[DOMAIN_NAMES]
        if spec_field.name == "map":
            annotation, options["default"] = str | None, None
        fields[spec_field.name] = (annotation, Field(**options))
        if spec_field.name == "map":
            fields["map_file"] = (str | None, MAP_FILE)
    return fields


_EnvironmentTable = create_model(
    "_EnvironmentTable", __base__=Table, __module__=__name__, **_table_fields()
)


class EnvironmentDefinition(_EnvironmentTable):
    """An environment of the study's own, ``[environments.NAME]``: used as the built-in ones
    are (list NAME in its domain's ``[[domains]]``). The map is text in the format of the
    built-in maps (docs: Designing your own environments), inline or in a file."""

    if TYPE_CHECKING:  # for the type checker, the fields that the code reads by name
        domain: str
        map: str | None

    @model_validator(mode="before")
    @classmethod
    def _former_key(cls, data: Any) -> Any:
        """``family``, the key's former name, read as ``domain``."""
        if not isinstance(data, dict) or "family" not in data:
            return data
        if "domain" in data:
            raise ValueError("give domain or family (its former name), not both")
        data = dict(data)
        data["domain"] = data.pop("family")
        return data

    @model_validator(mode="before")
    @classmethod
    def _read_map_file(cls, data: Any, info: ValidationInfo) -> Any:
        if not isinstance(data, dict) or data.get("map_file") is None:
            return data
        if data.get("map") is not None:
            raise ValueError("give map or map_file, not both")
        base = (info.context or {}).get("base", Path.cwd())
        path = Path(base) / str(data["map_file"])
        try:
            text = path.read_text(encoding="utf-8")
        except OSError as error:
            raise ValueError(f"cannot read map_file {path}: {error.strerror or error}") from None
        return {**data, "map": text}

    @model_validator(mode="after")
    def _check_map(self, info: ValidationInfo) -> EnvironmentDefinition:
        """Every problem of the map at once (the study's limit on states in the context)."""
        if self.map is None:
            raise ValueError("needs map (the map's text) or map_file")
        limit = (info.context or {}).get("max_states", DEFAULT_MAX_STATES)
        problems = self.spec("environment").problems(limit)
        if problems:
            raise ValueError("\n    ".join(str(problem) for problem in problems))
        return self

    def spec(self, name: str) -> EnvironmentSpec:
        """The environment as ``server.domains`` builds it, called ``name``."""
        assert self.map is not None
        return EnvironmentSpec(name=name, **self.model_dump(exclude={"map_file"}))


class Domain(Table):
    """A domain participants may be assigned to (least-filled first), and what they teach in it."""

    name: str = Field(description="The domain: navigation, farming or gravity.")
    environments: tuple[str, ...] = Field(
        min_length=1,
        description="The domain's environments taught, in this order (each once), e.g. "
        '["two-rooms", "doorway"].',
    )
    tutorial: str | None = Field(
        None,
        description="The tutorial's environment (one of the domain's); unset: the domain's own "
        "tutorial environment.",
    )

    @model_validator(mode="after")
    def _known(self) -> Domain:
        from server import domains

        if self.name not in domains.DOMAINS:
            raise ValueError(f"unknown domain {self.name!r}; valid: {', '.join(domains.DOMAINS)}")
        # The built-in names of another domain; the study's own are checked by StudyConfig.
        for environment in self.environments:
            if environment in domains.NAMES and domains.domain_of(environment) != self.name:
                raise ValueError(
                    f"environment {environment!r} is not in domain {self.name!r}; "
                    f"valid: {', '.join(domains.DOMAINS[self.name])}"
                )
        if len(set(self.environments)) != len(self.environments):
            raise ValueError(f"domain {self.name!r} lists an environment twice")
        if (
            self.tutorial is not None
            and self.tutorial in domains.NAMES
            and domains.domain_of(self.tutorial) != self.name
        ):
            raise ValueError(f"tutorial {self.tutorial!r} is not an environment of {self.name!r}")
        return self

    @property
    def tutorial_environment(self) -> str:
        from server import domains

        return self.tutorial or domains.TUTORIALS[self.name]
