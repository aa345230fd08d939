"""How participants finish on their platform (``[completion]``) and the study as
``bam-study prolific create`` makes it on Prolific (``[prolific]``), with Prolific's own rules
on ids and times."""

from __future__ import annotations

import math
import re
from decimal import Decimal
from urllib.parse import urlsplit

from pydantic import Field, field_validator, model_validator

from server.app.platform_registry import PlatformName
from server.app.study_file.base import Table


class Completion(Table):
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


class ProlificStudy(Table):
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
