"""What a simulation run is: the experiment, environments, learners, number of agents and
rounds, the seed and any learner settings that override the defaults. Everything here is
checked before a run touches its output folder.

The domains and learners are imported where they are used: ``bam-study --help`` imports this
module to list the experiments and should not pay for compiling the learners."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

# Experiment (paper section 4) -> the learners it compares by default.
EXPERIMENTS: dict[str, tuple[str, ...]] = {
    "demonstrations": ("bam", "model-based", "cloning"),  # section 4.2
    "global-cost": ("bam", "model-based", "global-cost"),  # section 4.3
    "feedback": ("bam", "model-based", "cloning"),  # section 4.4
}

DESCRIPTIONS: dict[str, str] = {
    "demonstrations": "Learning from demonstration (paper section 4.2): each round, one optimal "
    "demonstration per task, then an update.",
    "global-cost": "Global cost functions (paper section 4.3): the demonstration protocol, "
    "comparing BAM with model-based IRL with and without a learned global cost.",
    "feedback": "Demonstrations and feedback (paper section 4.4): each round, one demonstration "
    "per task and an update, then one horizon-long episode per task under the agent's greedy "
    "policy with A-SABL feedback from the simulated teacher, then an update.",
}


class ConfigError(ValueError):
    """A bad argument: reported to the user, nothing touched."""


@dataclass(frozen=True)
class RunConfig:
    """The arguments that determine a run's numbers (not how it is executed)."""

    experiment: str
    environments: tuple[str, ...]
    learners: tuple[str, ...]
    agents: int
    rounds: int
    seed: int
    # learner -> settings that override its defaults (only settings the learner has).
    learner_settings: dict[str, dict[str, Any]] = field(default_factory=dict)

    def settings_of(self, learner: str) -> dict[str, Any]:
        return dict(self.learner_settings.get(learner, {}))

    def effective_settings(self) -> dict[str, dict[str, Any]]:
        """Every setting of every learner of the run: its defaults with the overrides."""
        from server import learners

        return {
            name: dict(
                sorted(
                    {
                        **learners.learner_class(name).default_settings,
                        **self.settings_of(name),
                    }.items()
                )
            )
            for name in self.learners
        }

    def to_json(self) -> dict[str, Any]:
        return {
            "experiment": self.experiment,
            "environments": list(self.environments),
            "learners": list(self.learners),
            "agents": self.agents,
            "rounds": self.rounds,
            "seed": self.seed,
            "learner_settings": {
                name: dict(sorted(values.items()))
                for name, values in sorted(self.learner_settings.items())
            },
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> RunConfig:
        return cls(
            experiment=str(data["experiment"]),
            environments=tuple(data["environments"]),
            learners=tuple(data["learners"]),
            agents=int(data["agents"]),
            rounds=int(data["rounds"]),
            seed=int(data["seed"]),
            learner_settings={k: dict(v) for k, v in data.get("learner_settings", {}).items()},
        )


def _ordered_unique(names: Iterable[str], registry: Sequence[str]) -> tuple[str, ...]:
    """Names in the registry's order, each once (the order of the arguments does not change
    a run)."""
    given = set(names)
    return tuple(name for name in registry if name in given)


def parse_setting_value(learner: str, name: str, text: str, default: Any) -> Any:
    """``text`` converted to the type of the learner's default for the setting."""

    def bad(expected: str) -> ConfigError:
        return ConfigError(
            f"--learner-setting {name}={text}: {learner!r} expects {expected} (default {default!r})"
        )

    if isinstance(default, bool):
        lowered = text.strip().lower()
        if lowered in ("true", "yes", "1"):
            return True
        if lowered in ("false", "no", "0"):
            return False
        raise bad("true or false")
    if isinstance(default, int):
        try:
            return int(text)
        except ValueError:
            raise bad("an integer") from None
    if isinstance(default, float):
        try:
            value = float(text)
        except ValueError:
            raise bad("a number") from None
        if not math.isfinite(value):
            raise bad("a finite number")
        return value
    return text


def parse_learner_settings(
    assignments: Sequence[str], selected: Sequence[str]
) -> tuple[dict[str, dict[str, Any]], list[str]]:
    """``NAME=VALUE`` assignments -> per selected learner, the settings it has; and notes
    about settings that apply to none of the selected learners. A name that no registered
    learner has is an error (it is a typo, not a setting)."""
    from server import learners

    raw: dict[str, str] = {}
    for assignment in assignments:
        name, sep, value = assignment.partition("=")
        name = name.strip()
        if not sep or not name:
            raise ConfigError(f"--learner-setting expects NAME=VALUE, got {assignment!r}")
        raw[name] = value.strip()  # the last assignment of a name wins
    known = {name for cls in learners.LEARNERS.values() for name in cls.default_settings}
    unknown = sorted(set(raw) - known)
    if unknown:
        raise ConfigError(
            f"unknown learner setting(s): {', '.join(unknown)}; valid: {', '.join(sorted(known))}"
        )
    per_learner: dict[str, dict[str, Any]] = {}
    for learner in selected:
        defaults = learners.learner_class(learner).default_settings
        values = {
            name: parse_setting_value(learner, name, text, defaults[name])
            for name, text in raw.items()
            if name in defaults
        }
        if values:
            per_learner[learner] = values
    notes = [
        f"learner setting {name!r} applies to none of the learners of this run "
        f"({', '.join(selected)}); ignored"
        for name in raw
        if not any(name in learners.learner_class(ln).default_settings for ln in selected)
    ]
    return per_learner, notes


def build_config(
    experiment: str,
    environments: Sequence[str] | None,
    learner_names: Sequence[str] | None,
    agents: int,
    rounds: int,
    seed: int,
    setting_assignments: Sequence[str] = (),
) -> tuple[RunConfig, list[str]]:
    """A checked run configuration and notes for the user (raises ``ConfigError``)."""
    from server import domains, learners

    if experiment not in EXPERIMENTS:
        raise ConfigError(f"unknown experiment {experiment!r}; valid: {', '.join(EXPERIMENTS)}")
    environments = list(domains.ENVIRONMENTS) if not environments else list(environments)
    bad_environments = [name for name in environments if name not in domains.names()]
    if bad_environments:
        raise ConfigError(
            f"unknown environment(s): {', '.join(bad_environments)}; "
            f"valid: {', '.join(domains.names())}"
        )
    learner_names = list(EXPERIMENTS[experiment]) if not learner_names else list(learner_names)
    bad_learners = [name for name in learner_names if name not in learners.NAMES]
    if bad_learners:
        raise ConfigError(
            f"unknown learner(s): {', '.join(bad_learners)}; valid: {', '.join(learners.NAMES)}"
        )
    for name, value in (("agents", agents), ("rounds", rounds)):
        if value < 1:
            raise ConfigError(f"--{name} must be at least 1, got {value}")
    if seed < 0:
        raise ConfigError(f"--seed must be a non-negative integer, got {seed}")
    selected = _ordered_unique(learner_names, learners.NAMES)
    per_learner, notes = parse_learner_settings(setting_assignments, selected)
    config = RunConfig(
        experiment=experiment,
        environments=_ordered_unique(environments, domains.names()),
        learners=selected,
        agents=int(agents),
        rounds=int(rounds),
        seed=int(seed),
        learner_settings=per_learner,
    )
    # Let each learner check its own settings (e.g. an optimizer name) now, not in a worker.
    env = domains.make(config.environments[0])
    for learner in config.learners:
        try:
            learners.make(learner, env, seed=0, **config.settings_of(learner))
        except (TypeError, ValueError) as error:
            raise ConfigError(f"learner {learner!r}: {error}") from None
    return config, notes
