"""The study configuration: which domains and environments are taught, in which order, by which
learners, the tutorial, the texts shown to participants and how they complete.

A TOML file (``BAM_STUDY_CONFIG``); the default, ``server/config/study.toml``, is the paper's
study. ``load_study_config`` validates it against the environment and learner registries and
reports every problem with its place in the file. A study may define environments of its own
(``[environments.NAME]``, each map checked for every problem, with its line and column);
``StudyConfig.register_environments`` makes them known to ``server.domains`` by name.

Over 500 lines: the whole schema of the study file with its checks and messages, in one module,
because the docs' tables of keys are generated from it and a key is described where it is
checked.
"""

from __future__ import annotations

import difflib
import math
import re
import tomllib
from decimal import Decimal
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal, get_args, get_origin
from urllib.parse import urlsplit

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from server.app.platform_registry import PlatformName
from server.domains.spec import DEFAULT_MAX_STATES

if TYPE_CHECKING:
    from server.domains.spec import EnvironmentSpec

DEFAULT_STUDY_CONFIG = Path(__file__).resolve().parent.parent / "config" / "study.toml"


class StudyConfigError(ValueError):
    """The study configuration file is missing, not TOML, or not a valid study."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Colour(_Strict):
    """An agent's colour: a name participants can read and the colour to draw."""

    name: str = Field(
        min_length=1, max_length=40, description="The colour's name, shown to participants."
    )
    hex: str = Field(pattern=r"^#[0-9A-Fa-f]{6}$", description="The colour drawn, as #RRGGBB.")


class EnvironmentDefinition(_Strict):
    """An environment of the study's own, ``[environments.NAME]``: used as the built-in ones
    are (list NAME in its family's ``[[domains]]``). The map is text in the format of the
    built-in maps (docs: Designing your own environments), inline or in a file."""

    family: Literal["navigation", "gravity", "farming"] = Field(
        description="The environment's family: navigation, gravity or farming."
    )
    map: str | None = Field(
        None,
        description="The map's text: header lines (task:, start:, gravity of ...:), the column "
        "digits, then one numbered line per row.",
    )
    map_file: str | None = Field(
        None,
        description="Instead of map: a file holding the map, its path relative to the study file.",
    )
    horizon: int | None = Field(
        None,
        ge=1,
        le=1000,
        description="Steps per task; unset: the family's own (navigation 2 x (width + height), "
        "gravity and farming 4 x (width + height)).",
    )
    colours: dict[str, str] = Field(
        default_factory=dict,
        description="The colour drawn for each new terrain, machine or gravity colour, e.g. "
        '{ vines = "#6b8e23" }.',
    )
    gravity_colours: dict[str, str] = Field(
        default_factory=dict,
        description="Gravity only: colours beyond orange (o), green (g) and purple (p), "
        'each a lower-case letter and its name, e.g. { y = "yellow" }.',
    )
    gravity: dict[str, str] = Field(
        default_factory=dict,
        description="Gravity only: the gravity each colour sets (north, south, east or west); "
        "the map's 'gravity of COLOUR:' lines may give it instead.",
    )
    terrains: dict[str, str] = Field(
        default_factory=dict,
        description="Farming only: field terrains beyond soil (s), grass (i) and crops (c), "
        'each a lower-case letter and its name, e.g. { v = "vines" }.',
    )
    machines: dict[str, str] = Field(
        default_factory=dict,
        description="Farming only: machines beyond the plow (P), sprinkler (W) and harvester "
        '(H), each a capital letter and its name, e.g. { T = "trellis" }.',
    )
    works_on: dict[str, str] = Field(
        default_factory=dict,
        description="Farming only: the terrain each machine enters (required for a new "
        'machine; the others keep theirs unless given), e.g. { trellis = "vines" }.',
    )
    max_trapped_start_share: float = Field(
        0.0,
        ge=0,
        le=1,
        description="The share of a task's start probability (the simulations' or the user "
        "study's) that may lie on starts from which its goal can never be reached, whatever "
        "the agent does; 0: none (bam-study check names them).",
    )

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
        from server.domains.spec import EnvironmentSpec

        assert self.map is not None
        return EnvironmentSpec(
            name=name,
            family=self.family,
            map=self.map,
            horizon=self.horizon,
            colours=dict(self.colours),
            gravity_colours=dict(self.gravity_colours),
            gravity=dict(self.gravity),
            terrains=dict(self.terrains),
            machines=dict(self.machines),
            works_on=dict(self.works_on),
            max_trapped_start_share=self.max_trapped_start_share,
        )


class Domain(_Strict):
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


class Tutorial(_Strict):
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


Cell = tuple[int, int]


class AttentionChecks(_Strict):
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


class DeviceCheck(_Strict):
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


class Completion(_Strict):
    """How a participant finishes: MTurk's externalSubmit, Prolific's redirect, or a code page."""

    mode: PlatformName = Field(
        description="The platform the study runs on (one of server.app.platform_registry's): "
        "mturk: the page submits to MTurk's externalSubmit (turkSubmitTo); "
        "prolific: the page sends the participant to prolific_url; lab: the page shows a "
        "completion code to hand to the experimenter."
    )
    prolific_code: str | None = Field(
        None,
        pattern=r"^[A-Za-z0-9_\-]{1,64}$",
        description="The study's Prolific completion code (required with mode prolific).",
    )
    prolific_no_consent_code: str | None = Field(
        None,
        pattern=r"^[A-Za-z0-9_\-]{1,64}$",
        description="The study's Prolific NO_CONSENT completion code: a participant who declines "
        "consent is sent to prolific_url with it, and one who withdraws is given a button "
        "there, so that Prolific asks them to return the submission (without it, the page asks "
        "them to return it themselves).",
    )
    prolific_incompatible_device_code: str | None = Field(
        None,
        pattern=r"^[A-Za-z0-9_\-]{1,64}$",
        description="The study's Prolific INCOMPATIBLE_DEVICE completion code: a participant "
        "whose device fails the device check is sent to prolific_url with it, so that Prolific "
        "asks them to return the submission (without it, the page asks them to return it).",
    )
    prolific_url: str = Field(
        "https://app.prolific.com/submissions/complete?cc={code}",
        description="Where a Prolific participant is sent at the end: an https URL with "
        "{code}, which is replaced by prolific_code.",
    )

    @model_validator(mode="after")
    def _prolific_needs_code(self) -> Completion:
        if self.mode == "prolific":
            if self.prolific_code is None:
                raise ValueError("completion mode 'prolific' needs prolific_code")
            if urlsplit(self.prolific_url).scheme != "https" or "{code}" not in self.prolific_url:
                raise ValueError("prolific_url must be an https URL containing '{code}'")
        return self

    def prolific_redirect(self, code: str | None = None) -> str:
        return self.prolific_url.replace("{code}", code or self.prolific_code or "")


# Prolific's study link: PROLIFIC_PID, STUDY_ID and SESSION_ID, as the arrival reads them
# (``/study``), each filled in by Prolific from its placeholder.
PROLIFIC_LINK_QUERY = (
    "PROLIFIC_PID={{%PROLIFIC_PID%}}&STUDY_ID={{%STUDY_ID%}}&SESSION_ID={{%SESSION_ID%}}"
)
PROLIFIC_ID = r"^[0-9a-f]{24}$"


def prolific_least_maximum_minutes(estimated: int) -> int:
    """The least ``maximum_allowed_time`` Prolific accepts for an estimate of ``estimated``
    minutes: "two minutes plus two times the estimated time plus two times the square root of
    the estimated time" (its API reference; the participant help page's 2 + X + 2√X is the
    lower, so this one is kept), rounded up to a whole minute."""
    return math.ceil(2 + 2 * estimated + 2 * math.sqrt(estimated))


class ProlificStudy(_Strict):
    """The study as ``bam-study prolific create`` makes it on Prolific (with completion mode
    prolific): what participants see there, the places and the pay, the times, who may not
    take part, and the server's address that participants open."""

    name: str = Field(
        min_length=1, max_length=255, description="The study's name, shown to participants."
    )
    description: str = Field(
        min_length=1,
        description="The study's description on Prolific, shown before a participant takes part.",
    )
    places: int = Field(
        ge=1,
        description="Participants wanted (total_available_places); `bam-study prolific "
        "add-places` raises it later (places only go up once published).",
    )
    reward: Decimal = Field(
        gt=0,
        max_digits=8,
        decimal_places=2,
        description="The pay of one participant, in the workspace's currency "
        "(BAM_PROLIFIC_CURRENCY), at most two decimals: 6.50; sent to Prolific in cents.",
    )
    bonus_budget: Decimal | None = Field(
        None,
        gt=0,
        max_digits=10,
        decimal_places=2,
        description="The most the study's bonuses may come to, in the workspace's currency "
        "(before Prolific's fees and VAT): the dashboard refuses a bonus that would take the "
        "bonuses recorded (paid, or perhaps paid) past it, before anything is sent. Left out: "
        "no cap.",
    )
    estimated_minutes: int = Field(
        ge=1, description="How long the study takes, in minutes (estimated_completion_time)."
    )
    maximum_minutes: int = Field(
        ge=1,
        description="The longest a participant may take, in minutes (maximum_allowed_time): "
        "at least Prolific's least maximum for the estimate (2 + 2X + 2√X minutes for an "
        "estimate of X: 73 for 30), under 24 hours.",
    )
    previous_studies_blocklist: tuple[str, ...] = Field(
        (),
        description="Prolific study ids whose participants may not take part (a pilot, an "
        "earlier run of this study).",
    )
    workspace_id: str | None = Field(
        None,
        pattern=PROLIFIC_ID,
        description="The Prolific workspace whose participant groups the study uses (24 "
        "hexadecimal digits); needed only with a group below when the account has several "
        "workspaces.",
    )
    family_group: str | None = Field(
        None,
        min_length=1,
        max_length=200,
        description="The name of a participant group for the study's family (its pilot, its "
        "runs): whoever finished a study of the family is in it and may not take part in the "
        "next (participant_group_blocklist), and this study's finishers join it (the completion "
        "code's ADD_TO_PARTICIPANT_GROUP). `bam-study prolific create` makes the group in the "
        "workspace when it has none of that name.",
    )
    follow_up_group: str | None = Field(
        None,
        min_length=1,
        max_length=200,
        description="The name of a participant group that this study's finishers join (the "
        "completion code's ADD_TO_PARTICIPANT_GROUP), for a follow-up study whose only_group it "
        "is; made when the workspace has none of that name.",
    )
    only_group: str | None = Field(
        None,
        min_length=1,
        max_length=200,
        description="Only members of this participant group may take part "
        "(participant_group_allowlist): a follow-up study of an earlier one's follow_up_group.",
    )
    public_url: str = Field(
        description="The server's public https address, e.g. https://study.example.org: "
        "participants open {public_url}/study with Prolific's PROLIFIC_PID, STUDY_ID and "
        "SESSION_ID."
    )

    @field_validator("previous_studies_blocklist")
    @classmethod
    def _study_ids(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        bad = [v for v in value if not re.fullmatch(PROLIFIC_ID, v)]
        if bad:
            raise ValueError(
                f"{', '.join(repr(v) for v in bad)}: a Prolific study id is 24 hexadecimal digits"
            )
        return tuple(dict.fromkeys(value))

    @field_validator("public_url")
    @classmethod
    def _public_https(cls, value: str) -> str:
        parts = urlsplit(value)
        if parts.scheme != "https" or not parts.hostname:
            raise ValueError(f"{value!r}: the server's public address starts with https://")
        if parts.query or parts.fragment or "{" in value:
            raise ValueError(
                f"{value!r}: the server's address only (the study link's parameters are added)"
            )
        return value.rstrip("/")

    @model_validator(mode="after")
    def _times(self) -> ProlificStudy:
        if self.maximum_minutes >= 24 * 60:
            raise ValueError(
                f"maximum_minutes ({self.maximum_minutes}) must be under 24 hours (1440 minutes)"
            )
        if self.maximum_minutes < self.estimated_minutes:
            raise ValueError(
                f"maximum_minutes ({self.maximum_minutes}) is less than estimated_minutes "
                f"({self.estimated_minutes})"
            )
        floor = prolific_least_maximum_minutes(self.estimated_minutes)
        if self.maximum_minutes < floor:
            raise ValueError(
                f"maximum_minutes ({self.maximum_minutes}) is below Prolific's least maximum "
                f"time for estimated_minutes {self.estimated_minutes}: {floor} (2 + 2 x "
                "estimate + 2 x its square root, in minutes); Prolific refuses the study"
            )
        return self

    @property
    def reward_cents(self) -> int:
        return int(self.reward * 100)

    def study_link(self, base_url: str | None = None) -> str:
        """Prolific's external_study_url: the study page of ``base_url`` (default: the public
        address) with Prolific's placeholders."""
        return f"{(base_url or self.public_url).rstrip('/')}/study?{PROLIFIC_LINK_QUERY}"


QUESTION_ID = r"^[a-z][a-z0-9_]{0,63}$"


def _distinct_texts(value: tuple[str, ...], problem: str) -> tuple[str, ...]:
    if any(not text.strip() for text in value) or len(set(value)) != len(value):
        raise ValueError(problem)
    return value


class _Question(_Strict):
    id: str = Field(
        pattern=QUESTION_ID,
        description="The question's name in the data (questionnaire_answers.csv): lower-case "
        "letters, digits and '_'.",
    )
    text: str = Field(min_length=1, max_length=1000, description="The question, as shown.")
    required: bool = Field(True, description="The participant must answer it to finish.")


class TextQuestion(_Question):
    """A free-text answer."""

    kind: Literal["text"] = Field(description="text: free text.")
    max_length: int = Field(1000, ge=1, le=10_000, description="Longest answer, in characters.")
    lines: int = Field(4, ge=1, le=20, description="Height of the answer box, in lines.")


class LikertQuestion(_Question):
    """A point on a scale, each point with its label, stored as 1 to the number of points."""

    kind: Literal["likert"] = Field(description="likert: a point on a labelled scale.")
    labels: tuple[str, ...] = Field(
        min_length=2,
        max_length=11,
        description="The scale's points from the first (1) to the last, each with its label.",
    )

    @field_validator("labels")
    @classmethod
    def _distinct(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        return _distinct_texts(value, "each point of the scale needs its own, non-empty label")


class ChoiceQuestion(_Question):
    """One of a few answers (multiple choice), stored as the text of the one picked."""

    kind: Literal["choice"] = Field(description="choice: one of the choices.")
    choices: tuple[str, ...] = Field(
        min_length=2, max_length=20, description="The answers offered, in the order shown."
    )

    @field_validator("choices")
    @classmethod
    def _distinct(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        return _distinct_texts(value, "each choice must be a different, non-empty text")


Question = Annotated[TextQuestion | LikertQuestion | ChoiceQuestion, Field(discriminator="kind")]


class Questionnaire(_Strict):
    """Questions asked after the last agent, before the completion code (none by default)."""

    intro: str = Field(
        "Before you get your completion code, please answer a few questions about the study.",
        min_length=1,
        description="Shown above the questions.",
    )
    questions: tuple[Question, ...] = Field(
        default=(),
        max_length=50,
        description="Each a [[questionnaire.questions]] table with kind = 'text', 'likert' or "
        "'choice'.",
    )

    @field_validator("questions")
    @classmethod
    def _unique_ids(cls, value: tuple[Question, ...]) -> tuple[Question, ...]:
        ids = [question.id for question in value]
        if len(set(ids)) != len(ids):
            raise ValueError("two questions have the same id")
        return value

    def largest_answers_bytes(self) -> int:
        """The largest JSON body the answers can take (every character escaped, as \\uXXXX)."""
        size = 256
        for question in self.questions:
            size += 80 + len(question.id)
            if isinstance(question, TextQuestion):
                size += 6 * question.max_length
            elif isinstance(question, ChoiceQuestion):
                size += 6 * max(len(choice) for choice in question.choices)
        return size


class DatasetRelease(_Strict):
    """The study's data as a release (``bam-study export --format croissant``, ``datapackage``,
    ``psych-ds``, ``parquet``): what only the authors can say about it. The export fills
    everything the server knows (platform, dates, counts, pay, consent, pseudonyms, erasures);
    a field left out here is listed as not answered, never made up."""

    title: str | None = Field(
        None,
        min_length=1,
        max_length=300,
        description="The dataset's name (default: the study's title).",
    )
    description: str | None = Field(
        None, min_length=1, description="What the dataset holds and why it was collected."
    )
    license: str | None = Field(
        None,
        min_length=1,
        max_length=100,
        pattern=r"^[A-Za-z0-9.+-]+$",
        description="The data's licence as an SPDX id (CC-BY-4.0, CC0-1.0, ODbL-1.0, ...).",
    )
    url: str | None = Field(
        None,
        pattern=r"^https?://\S+$",
        description="Where the dataset is published (http or https).",
    )
    version: str | None = Field(
        None,
        min_length=1,
        max_length=40,
        description="The release's version (1.0.0), for a dataset published more than once.",
    )
    authors: tuple[str, ...] = Field(
        (), description="The people who collected and curated the data, one string each."
    )
    citation: str | None = Field(
        None, min_length=1, description="How to cite the dataset (a reference or a BibTeX entry)."
    )
    keywords: tuple[str, ...] = Field((), description="Words to find the dataset by.")
    annotator_demographics: str | None = Field(
        None,
        min_length=1,
        description="Who the participants were (Croissant's rai:annotatorDemographics), as far "
        "as the authors know it: the server asks no demographic question.",
    )
    biases: str | None = Field(
        None, min_length=1, description="Known biases of the data (rai:dataBiases)."
    )
    use_cases: str | None = Field(
        None,
        min_length=1,
        description="What the data is for, and what it is not fit for (rai:dataUseCases).",
    )
    social_impact: str | None = Field(
        None, min_length=1, description="The data's possible social impact (rai:dataSocialImpact)."
    )
    limitations: str | None = Field(
        None,
        min_length=1,
        description="Known limits beyond what the server records (rai:dataLimitations), such "
        "as simulated participants.",
    )


class StudyConfig(_Strict):
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
        "lower-case letters, digits and '-'), listed in a domain of their family.",
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
        """Each domain's environments are built in or the study's own, of its family (each
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
                elif own.family != domain.name:
                    problems.append(
                        f"{where[environment]}: domain {domain.name!r}: {environment!r} is a "
                        f"{own.family} environment"
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
