"""Reading a study file: ``load_study_config`` (a TOML file, the paper's study by default) and
``parse_study_config`` (its data) validate it and report every problem with its place in the
file, an unknown key with the nearest valid one."""

from __future__ import annotations

import difflib
import re
import tomllib
from pathlib import Path
from typing import Any, get_args, get_origin

from pydantic import BaseModel, ValidationError

from server.app.study_file.study import StudyConfig
from server.domains.spec import DEFAULT_MAX_STATES

DEFAULT_STUDY_CONFIG = Path(__file__).resolve().parents[2] / "config" / "study.toml"


class StudyConfigError(ValueError):
    """The study configuration file is missing, not TOML, or not a valid study."""


def parse_study_config(
    data: dict[str, Any], source: str = "study configuration", base: Path | None = None
) -> StudyConfig:
    """Validate a study's data (``base``: the directory map files are relative to)."""
    try:
        limit = data.get("max_environment_states", DEFAULT_MAX_STATES)
        if not isinstance(limit, int) or isinstance(limit, bool):
            limit = DEFAULT_MAX_STATES  # the field reports the bad value
        context = {"base": base or Path.cwd(), "max_states": limit}
        return StudyConfig.model_validate(data, context=context)
    except ValidationError as error:
        raise StudyConfigError(f"{source} is not a valid study:\n{_format_errors(error)}") from None


def load_study_config(path: Path | str | None = None) -> StudyConfig:
    """Read and validate a study configuration (the paper's study when ``path`` is None)."""
    path = Path(path) if path is not None else DEFAULT_STUDY_CONFIG
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as error:
        raise StudyConfigError(f"cannot read the study configuration {path}: {error}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise StudyConfigError(f"{path} is not valid TOML: {error}") from None
    return parse_study_config(data, str(path), path.resolve().parent)


def _format_errors(error: ValidationError) -> str:
    lines = []
    for item in error.errors():
        where = ".".join(str(part) for part in item["loc"]) or "(top level)"
        message = item["msg"].removeprefix("Value error, ")
        if not item["loc"] and _LOCATED.match(message):  # a whole-study check names its places
            lines.append(f"  {message}")
            continue
        if item["type"] == "union_tag_not_found":  # a question without its kind
            message = "needs kind = 'text', 'likert' or 'choice'"
        elif item["type"] == "extra_forbidden":
            message = _unknown_key(item["loc"])
        lines.append(f"  {where}: {message}")
    return "\n".join(lines)


# A problem that a check of the whole study found, named by its place ("domains.0.tutorial: ...").
_LOCATED = re.compile(r"^[a-z_]+(\.[A-Za-z0-9_-]+)*: ")


def _unknown_key(loc: tuple[int | str, ...]) -> str:
    """A key no table at ``loc`` has: the nearest valid key, or all of them."""
    valid = sorted(_keys_at(loc[:-1]))
    nearest = difflib.get_close_matches(str(loc[-1]), valid, n=1)
    if nearest:
        return f"unknown key; did you mean {nearest[0]}?"
    return f"unknown key; valid keys: {', '.join(valid)}"


def _keys_at(loc: tuple[int | str, ...]) -> set[str]:
    """The keys of the table at ``loc`` (list indexes skipped; a question's kind picks its
    class, as in Pydantic's locations)."""
    tables: list[type[BaseModel]] = [StudyConfig]
    keyed = False  # the tables are a mapping's values: the next part is a key of it
    for part in loc:
        if isinstance(part, int) or keyed:
            keyed = False
            continue
        kinds = [
            table
            for table in tables
            if "kind" in table.model_fields
            and part in get_args(table.model_fields["kind"].annotation)
        ]
        if len(tables) > 1 and kinds:
            tables = kinds
            continue
        fields = [table.model_fields[part] for table in tables if part in table.model_fields]
        if not fields:
            return set()
        tables = list(_tables_in(fields[0].annotation))
        keyed = get_origin(fields[0].annotation) is dict
    return {name for table in tables for name in table.model_fields}


def _tables_in(annotation: Any) -> set[type[BaseModel]]:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return {annotation}
    return {table for argument in get_args(annotation) for table in _tables_in(argument)}
