"""The platforms participants come from, by name: ``PLATFORMS``, the one list of them. Every
other list of platform names is derived from its keys (``names``, ``PlatformName``): the study
file's ``completion.mode``, the API's ``platform`` and ``mode`` fields, ``BAM_REVIEW_BACKEND``'s
choices, the platforms whose ids are scrubbed.

An entry is a ``Platform`` (``server.app.platforms.base``), or the ``"module:attribute"`` where
it is, imported the first time it is asked for. The names are here, at the root of the app, and
the platforms themselves in ``server.app.platforms``, which imports the study file's and the
settings' modules: those read the names from here without importing a platform.

A platform is added with one entry::

    PLATFORMS["connect"] = "server.app.platforms.connect:CONNECT"
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Annotated, Any

from pydantic import AfterValidator, Field

if TYPE_CHECKING:
    from server.app.platforms.base import Platform

PLATFORMS: dict[str, Platform | str] = {
    "lab": "server.app.platforms.lab:LAB",
    "mturk": "server.app.platforms.mturk:MTURK",
    "prolific": "server.app.platforms.prolific_platform:PROLIFIC",
}
_loaded: dict[str, Platform] = {}


def names() -> tuple[str, ...]:
    return tuple(PLATFORMS)


def platform(name: str) -> Platform:
    """The platform called ``name`` (KeyError for a name not in ``PLATFORMS``)."""
    entry = PLATFORMS[name]
    if not isinstance(entry, str):
        return entry
    if name not in _loaded:
        module, _, attribute = entry.partition(":")
        _loaded[name] = getattr(importlib.import_module(module), attribute)
    return _loaded[name]


def platforms() -> list[Platform]:
    return [platform(name) for name in PLATFORMS]


def arrival_parameters() -> dict[str, str]:
    """Every platform's study-link parameters, each with its value's pattern."""
    return {name: pattern for p in platforms() for name, pattern in p.parameters.items()}


def known_platform(name: str) -> str:
    """``name``, if it is a platform's (a ValueError that lists them otherwise)."""
    if name not in PLATFORMS:
        raise ValueError(f"{name!r} is not a platform: one of {', '.join(map(repr, PLATFORMS))}")
    return name


def _enum(schema: dict[str, Any]) -> None:
    schema["enum"] = list(PLATFORMS)


# A platform's name, checked against PLATFORMS as it stands (and so listed in JSON schemas).
PlatformName = Annotated[str, AfterValidator(known_platform), Field(json_schema_extra=_enum)]
