"""The study file's top level (``StudyConfig``): the texts, the domains and learners taught,
the agents' colours, the limits, and the tables of the other modules; with the checks that
need the whole study (each domain's environments, enough colours, attention checks between
agents, the learners' settings). The tutorial is here too, since its learner is checked as the
study's learners are."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from pydantic import Field, field_validator, model_validator

from server.app.study_file.base import Colour, Table
from server.app.study_file.checks import AttentionChecks, DeviceCheck
from server.app.study_file.dataset import DatasetRelease
from server.app.study_file.environments import Domain, EnvironmentDefinition
from server.app.study_file.platforms import Completion, ProlificStudy
from server.app.study_file.questionnaire import Questionnaire
from server.domains.spec import DEFAULT_MAX_STATES

if TYPE_CHECKING:
    from server.domains.spec import EnvironmentSpec


class Tutorial(Table):
    """The tutorial before the study's agents (its learning session is kept apart and not
    analysed)."""

    enabled: bool = Field(True, description="Run the tutorial before the study's agents.")
    learner: str = Field(
        "cloning", description="The tutorial agent's learner (one of the learner names)."
    )
    colour: Colour = Field(
        Colour(name="black", hex="#000000"), description="The tutorial agent's colour."
    )

    @field_validator("learner")
    @classmethod
    def _known_learner(cls, value: str) -> str:
        return _check_learner(value)


class StudyConfig(Table):
    title: str = Field(
        min_length=1, max_length=200, description="The study's title, shown on every page."
    )
    consent: str = Field(
        min_length=1,
        description="The consent text participants agree to (paragraphs separated by blank lines).",
    )
    payment: str = Field(min_length=1, description="The payment text shown with the consent.")
    completion: Completion = Field(description="How participants finish (the table below).")
    domains: tuple[Domain, ...] = Field(
        min_length=1,
        description="The domains; each participant is assigned one at consent, the "
        "least-filled first.",
    )
    learners: tuple[str, ...] = Field(
        min_length=1,
        description="The learners taught in each environment, in an order randomised per "
        "participant and environment: bam, model-based, global-cost or cloning.",
    )
    agents_per_environment: int | None = Field(
        None, ge=1, le=12, description="Defaults to one agent per learner."
    )
    learner_settings: dict[str, dict[str, Any]] = Field(
        default_factory=dict,
        description="Settings that override a learner's defaults, one table per learner: "
        "[learner_settings.bam] with alternations = 10, say.",
    )
    tutorial: Tutorial = Field(Tutorial(), description="The tutorial (the table below).")
    colours: tuple[Colour, ...] = Field(
        min_length=1,
        description="The agents' colours, by position among a participant's agents: at least "
        "as many as a participant's agents.",
    )
    allow_repeat_workers: bool = Field(
        False,
        description="Let a worker (the same MTurk or Prolific id) take part again after a "
        "participation that was not returned or declined.",
    )
    allow_anonymous: bool = Field(
        False, description="Accept arrivals without platform ids (a lab participant)."
    )
    reveal_gravity: bool = Field(False, description="Show gravity directions to participants.")
    max_active_participants: int | None = Field(
        None,
        ge=1,
        description="Participants in the study at once (arrived and not finished, seen in the "
        "last BAM_ACTIVE_MINUTES); an arrival beyond it waits on a page that lets them in as "
        "soon as a place frees. Default: the capacity the server measures at start (none "
        "before it has).",
    )
    scrub_identifiers_after_days: float = Field(
        30,
        ge=0,
        description="Days after a participant's last request after which their worker, "
        "assignment and Prolific ids and completion code are replaced by their pseudonyms in "
        "the database (as `bam-study db scrub` does): by default after the longest review "
        "window of the platforms (MTurk approves an assignment by itself after at most 30 "
        "days), so that reviews and bonuses can still name the worker until then.",
    )
    questionnaire: Questionnaire = Field(
        Questionnaire(),
        description="A post-study questionnaire, shown after the last agent and before the "
        "completion code; none when it has no questions.",
    )
    environments: dict[str, EnvironmentDefinition] = Field(
        default_factory=dict,
        description="The study's own environments, one [environments.NAME] table each (NAME: "
        "lower-case letters, digits and '-'), listed in their domain's [[domains]] table.",
    )
    attention_checks: AttentionChecks = Field(
        AttentionChecks(),
        description="Instructional attention checks between agents (the table below); none "
        "unless enabled.",
    )
    device_check: DeviceCheck = Field(
        DeviceCheck(),
        description="The check of the participant's device before consent (the table below); "
        "none unless enabled.",
    )
    prolific: ProlificStudy | None = Field(
        None,
        description="The study on Prolific, for `bam-study prolific create` (the table below).",
    )
    dataset: DatasetRelease = Field(
        DatasetRelease(),
        description="The study's data as a release: its title, licence, authors, citation and "
        "the answers only its authors can give (the table below); a key left out is listed "
        "as not answered.",
    )
    max_environment_states: int = Field(
        DEFAULT_MAX_STATES,
        ge=1,
        le=100_000,
        description="The most states (cells x gravities or machines carried) an environment "
        "of the study's own may have.",
    )

    @field_validator("learners")
    @classmethod
    def _known_learners(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        for name in value:
            _check_learner(name)
        return value

    @model_validator(mode="after")
    def _consistent(self) -> StudyConfig:
        from server.learners import learner_class

        names = [domain.name for domain in self.domains]
        if len(set(names)) != len(names):
            raise ValueError("a domain is listed twice")
        for name, settings in self.learner_settings.items():
            try:  # the learner's typed settings: unknown keys and wrong values refused
                learner_class(_check_learner(name)).settings_type.of(settings)
            except ValueError as error:
                raise ValueError(f"learner_settings.{name}: {error}") from None
        colour_names = [colour.name for colour in self.colours]
        if len(set(colour_names)) != len(colour_names):
            raise ValueError("two colours have the same name")
        self._check_environments()
        most = max(len(domain.environments) for domain in self.domains) * self.agents
        if len(self.colours) < most:
            raise ValueError(
                f"{len(self.colours)} colours for up to {most} agents: each agent needs its own"
            )
        if self.attention_checks.enabled and not self.attention_checks.after_agents(most):
            raise ValueError(
                f"attention_checks: every = {self.attention_checks.every} leaves no check "
                f"between agents (a participant teaches at most {most}; none after the last)"
            )
        return self

    @field_validator("environments")
    @classmethod
    def _environment_names(
        cls, value: dict[str, EnvironmentDefinition]
    ) -> dict[str, EnvironmentDefinition]:
        from server import domains
        from server.domains.spec import NAME

        for name in value:
            if name in domains.NAMES:
                raise ValueError(f"{name!r} is a built-in environment; choose another name")
            if not NAME.match(name):
                raise ValueError(
                    f"{name!r}: a name is lower-case letters, digits and '-', from a letter"
                )
        return value

    def _check_environments(self) -> None:
        """Each domain's environments are built in or the study's own, of its domain (each
        map was checked on its own)."""
        from server import domains

        problems: list[str] = []
        for number, domain in enumerate(self.domains):
            where = {name: f"domains.{number}.environments" for name in domain.environments}
            if domain.tutorial is not None:
                where[domain.tutorial] = f"domains.{number}.tutorial"
            for environment in (*domain.environments, domain.tutorial):
                if environment is None or environment in domains.NAMES:
                    continue
                own = self.environments.get(environment)
                if own is None:
                    problems.append(
                        f"{where[environment]}: domain {domain.name!r}: no environment "
                        f"{environment!r}; valid: "
                        f"{', '.join((*domains.DOMAINS[domain.name], *self.environments))}"
                    )
                elif own.domain != domain.name:
                    problems.append(
                        f"{where[environment]}: domain {domain.name!r}: {environment!r} is a "
                        f"{own.domain} environment"
                    )
        if problems:
            raise ValueError("\n    ".join(problems))

    def environment_specs(self) -> tuple[EnvironmentSpec, ...]:
        """The study's own environments, as ``server.domains`` registers them."""
        return tuple(definition.spec(name) for name, definition in self.environments.items())

    def register_environments(self) -> None:
        """Make the study's own environments known to ``server.domains`` by name."""
        from server import domains

        for spec in self.environment_specs():
            domains.register(spec, self.max_environment_states)

    @property
    def agents(self) -> int:
        """Agents taught per environment."""
        return self.agents_per_environment or len(self.learners)

    def domain(self, name: str) -> Domain:
        for domain in self.domains:
            if domain.name == name:
                return domain
        raise KeyError(name)

    def taught_environments(self) -> list[str]:
        """Every environment the study teaches, each domain's tutorial first, each once."""
        names = [
            name
            for domain in self.domains
            for name in (
                *((domain.tutorial_environment,) if self.tutorial.enabled else ()),
                *domain.environments,
            )
        ]
        return list(dict.fromkeys(names))

    def pairs(self) -> list[tuple[str, str]]:
        """Every (environment, learner) of the study's agents."""
        return [
            (environment, learner)
            for domain in self.domains
            for environment in domain.environments
            for learner in self.learners
        ]

    def settings_of(self, learner: str) -> dict[str, Any]:
        return dict(self.learner_settings.get(learner, {}))

    def public(self) -> dict[str, Any]:
        """What any visitor may read: texts and the shape of the study, no learner names."""
        return {
            "title": self.title,
            "consent": self.consent,
            "payment": self.payment,
            "completion_mode": self.completion.mode,
            "tutorial": self.tutorial.enabled,
            "agents_per_environment": self.agents,
            "reveal_gravity": self.reveal_gravity,
            "environments": self.taught_environments(),
            "questionnaire": self.questionnaire.model_dump(mode="json")
            if self.questionnaire.questions
            else None,
            "device_check": self.device_check.model_dump(mode="json")
            if self.device_check.enabled
            else None,
        }


def _check_learner(name: str) -> str:
    from server import learners

    if name not in learners.NAMES:
        raise ValueError(f"unknown learner {name!r}; valid: {', '.join(learners.NAMES)}")
    return name
