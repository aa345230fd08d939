"""The study file: which domains and environments are taught, in which order, by which
learners, the tutorial, the texts shown to participants and how they complete.

A TOML file (``BAM_STUDY_CONFIG``); the default, ``server/config/study.toml``, is the paper's
study. ``load_study_config`` validates it against the environment and learner registries and
reports every problem with its place in the file. A study may define environments of its own
(``[environments.NAME]``, each map checked for every problem, with its line and column);
``StudyConfig.register_environments`` makes them known to ``server.domains`` by name.

One module per part of the file, each key described where it is checked (the docs' tables of
keys are generated from these models): ``study`` (the top level and the tutorial),
``environments`` (the study's own environments and its domains), ``checks`` (the device and
attention checks), ``platforms`` (completion and the Prolific study), ``questionnaire``,
``dataset`` (the release's metadata) and ``loading`` (reading a file and reporting its
problems). Everything a caller uses is imported from here.
"""

from __future__ import annotations

from server.app.study_file.base import Colour, Table
from server.app.study_file.checks import AttentionChecks, Cell, DeviceCheck
from server.app.study_file.dataset import DatasetRelease
from server.app.study_file.environments import Domain, EnvironmentDefinition
from server.app.study_file.loading import (
    DEFAULT_STUDY_CONFIG,
    StudyConfigError,
    load_study_config,
    parse_study_config,
)
from server.app.study_file.platforms import (
    PROLIFIC_ID,
    PROLIFIC_LINK_QUERY,
    Completion,
    ProlificStudy,
    prolific_least_maximum_minutes,
)
from server.app.study_file.questionnaire import (
    QUESTION_ID,
    ChoiceQuestion,
    LikertQuestion,
    Question,
    Questionnaire,
    TextQuestion,
)
from server.app.study_file.study import StudyConfig, Tutorial

__all__ = [
    "DEFAULT_STUDY_CONFIG",
    "PROLIFIC_ID",
    "PROLIFIC_LINK_QUERY",
    "QUESTION_ID",
    "AttentionChecks",
    "Cell",
    "ChoiceQuestion",
    "Colour",
    "Completion",
    "DatasetRelease",
    "DeviceCheck",
    "Domain",
    "EnvironmentDefinition",
    "LikertQuestion",
    "ProlificStudy",
    "Question",
    "Questionnaire",
    "StudyConfig",
    "StudyConfigError",
    "Table",
    "TextQuestion",
    "Tutorial",
    "load_study_config",
    "parse_study_config",
    "prolific_least_maximum_minutes",
]
