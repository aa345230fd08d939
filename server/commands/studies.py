"""A study file's own environments for the commands that take ``--study``: loaded, checked
and registered by name (``server.domains``) and as Gymnasium ids (``server.rl``)."""

from __future__ import annotations

import re
from pathlib import Path


class StudyEnvironmentsError(ValueError):
    """The study file cannot be used (the message lists its problems)."""


def study_name(path: Path) -> str:
    """The study's name in Gymnasium ids: its file's name without ``.toml``."""
    return re.sub(r"[^A-Za-z0-9_-]", "-", path.stem) or "study"


def register_study(path: Path | str) -> tuple[str, ...]:
    """Register the study's own environments; returns their names in the study's order."""
    path = Path(path)
    from server.app.study_file import StudyConfigError, load_study_config
    from server.rl.environments import register_study_environments

    try:
        study = load_study_config(path)
    except StudyConfigError as error:
        raise StudyEnvironmentsError(str(error)) from None
    study.register_environments()
    names = tuple(study.environments)
    register_study_environments(study_name(path), names)
    return names
