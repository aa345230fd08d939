"""The learners' typed settings (``server.learners.settings``): every field typed and
described, values checked where they are made, and saved states restored as they were."""

from __future__ import annotations

import dataclasses
from typing import Any

import pytest

from server import domains, learners
from server.domains.base import GRADIENT_RULES
from server.learners import planning
from server.learners.settings import (
    KINDS,
    PLANNER_PRECISIONS,
    PlannerSettings,
    Settings,
)


@pytest.mark.parametrize("name", learners.NAMES)
def test_every_setting_is_typed_described_and_defaulted(name: str) -> None:
    settings_type = learners.learner_class(name).settings_type
    defaults = settings_type()
    for field in dataclasses.fields(settings_type):
        assert field.type in KINDS, (name, field.name, field.type)
        assert field.metadata["description"].strip(), (name, field.name)
        assert field.default is not dataclasses.MISSING, (name, field.name)
        assert getattr(defaults, field.name) == field.default
    described = settings_type.described()
    assert [info.name for info in described] == list(settings_type.names())
    assert learners.learner_class(name).default_settings == defaults.as_dict()


def test_the_choices_are_those_the_code_knows() -> None:
    assert PLANNER_PRECISIONS == tuple(planning.PRECISIONS)
    assert PlannerSettings.field("dynamics_gradient").metadata["choices"] == GRADIENT_RULES


@pytest.mark.parametrize(
    ("name", "changes", "message"),
    [
        ("bam", {"beta": "1"}, "beta must be a number, got '1'"),
        ("bam", {"beta": True}, "beta must be a number, got True"),
        ("bam", {"alternations": 2.0}, "alternations must be an integer, got 2.0"),
        ("cloning", {"steps": False}, "steps must be an integer, got False"),
        ("bam", {"normalized_actions": 1}, "normalized_actions must be true or false, got 1"),
        ("bam", {"momentum_clip": "norm"}, "momentum_clip must be one of 'step', 'velocity'"),
        ("bam", {"cost_cells": "some"}, "cost_cells must be one of 'domain', 'every'"),
        ("bam", {"dynamics_gradient": "mine"}, "dynamics_gradient must be one of 'authors'"),
        ("model-based", {"dynamics_prior_sd": 0}, "dynamics_prior_sd must be a positive number"),
        ("cloning", {"q_bound_sds": -1.0}, "q_bound_sds must be a positive number or None"),
        ("cloning", {"tie_tolerance": 1.0}, "tie_tolerance must be in [0, 1)"),
        ("global-cost", {"global_prior_sd": None}, "global_prior_sd must be a number"),
    ],
)
def test_a_value_of_the_wrong_type_or_choice_is_refused_by_name(
    name: str, changes: dict[str, Any], message: str
) -> None:
    env = domains.make("wall")
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace(")", r"\)")):
        learners.make(name, env, **changes)
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace(")", r"\)")):
        learners.learner_class(name).settings_type.of(changes)


def test_a_key_that_is_not_a_setting_is_refused_with_the_valid_ones() -> None:
    settings_type = learners.learner_class("cloning").settings_type
    with pytest.raises(ValueError) as error:
        settings_type.of({"stepz": 3})
    assert str(error.value).startswith("unknown setting(s) stepz; valid: alpha, beta,")
    assert "tie_tolerance" in str(error.value)


def test_settings_are_frozen_and_replaced_with_their_checks() -> None:
    settings = learners.make("bam", domains.make("wall")).settings
    with pytest.raises(dataclasses.FrozenInstanceError):
        settings.beta = 2.0  # type: ignore[misc]
    assert settings.replace(beta=2).beta == 2 and settings.beta == 1.0
    with pytest.raises(ValueError, match="warm_share must be a number greater than 0"):
        settings.replace(warm_share=0)


def test_a_learner_without_settings_takes_none() -> None:
    assert Settings.names() == () and Settings().as_dict() == {}
    with pytest.raises(ValueError, match="unknown setting"):
        Settings.of({"beta": 1.0})


@pytest.mark.parametrize("name", learners.NAMES)
def test_a_saved_state_keeps_its_settings_as_they_were(name: str) -> None:
    """The settings a state stores are the learner's, value for value and type for type (a
    state saved before a setting existed: test_optimizers.py)."""
    env = domains.make("wall")
    learner = learners.make(name, env, beta=2, epsilon=0.1)
    state = learners.loads(learners.dumps(learner.state_dict()))
    restored = learners.restore(env, state)
    assert restored.settings == learner.settings
    assert type(restored.settings.beta) is int and state["settings"]["beta"] == 2
    assert state["settings"] == learner.settings.as_dict()
