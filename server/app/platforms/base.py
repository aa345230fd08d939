"""The seam between the study and a platform participants come from: the ``Platform`` protocol,
and ``BasePlatform``, its defaults (a platform with no ids, no replica and no reviews: the lab).

A platform says:

- who arrives (``arrival``): its study link's URL parameters (``parameters``, each with the
  pattern its value matches) mapped onto the participant's three ids (``ids``: worker,
  assignment, study), checked, with where the submission goes (``submit_to``);
- how a participant finishes (``fixed_code``, ``handing``) and how one who declines consent or
  withdraws leaves (``no_consent_code``, ``withdrawal``);
- where its reviews go (``review_backend``), whose work is open to a decision
  (``awaits_decision``) and when the platform approves it by itself (``auto_approval_at``), its own rules for a rejection (``check_rejection``) and its status of
  the submission after a decision (``status_after``, kept in ``participants.platform_status``);
- the rows of its local replica that hold a participant's turn (``own_replica_rows``) or name
  them among others (``shared_replica_rows``), for scrubbing (erasure leaves them: the
  platform keeps its record).

The platforms are found by name in ``server.app.platform_registry.PLATFORMS``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from datetime import datetime
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

from server.app.errors import ApiError

if TYPE_CHECKING:
    from sqlalchemy import Connection, Table

    from server.app.platforms.review import ReviewBackend
    from server.app.settings import Settings
    from server.app.storage.db import Database
    from server.app.storage.vocabulary import ReviewDecision
    from server.app.study_file import StudyConfig

ID_PATTERN = r"^[A-Za-z0-9_\-]{1,128}$"

Rows = list[tuple["Table", Any]]  # (table, condition)


@dataclass(frozen=True)
class ArrivalIds:
    """One arrival's platform and the participant's ids there (none in a lab)."""

    name: str  # the platform's
    platform_participant_id: str | None = None  # MTurk's workerId, Prolific's PROLIFIC_PID
    platform_submission_id: str | None = None  # MTurk's assignmentId, Prolific's SESSION_ID
    platform_study_id: str | None = None  # MTurk's hitId, Prolific's STUDY_ID
    submit_to: str | None = None  # where the completion is submitted, when the link says


@dataclass(frozen=True)
class Handing:
    """How the completion code is handed in: a form posted (``submit_url`` with
    ``submit_fields``), a redirect, or neither (the page shows the code)."""

    submit_url: str | None = None
    submit_fields: dict[str, str] | None = None
    redirect_url: str | None = None


@dataclass(frozen=True)
class Leaving:
    """What a participant who withdrew is told, and where they are sent (if anywhere)."""

    message: str
    redirect_url: str | None = None


@dataclass(frozen=True)
class Released:
    """A participant whose turn the platform released (returned, timed out) and gave to
    another: the page that turns them away on arrival, and the refusal of their requests."""

    title: str
    message: str
    detail: str


class Platform(Protocol):
    """One platform participants come from (``BasePlatform`` gives the defaults)."""

    name: str  # its key in PLATFORMS, stored in participants.platform
    display_name: str  # in the participants' pages: "Mechanical Turk"
    # The study link's URL parameters (empty: none, a lab), each with its value's pattern.
    parameters: Mapping[str, str]
    # Which of them holds which of the participant's ids (platform_participant_id,
    # platform_submission_id, platform_study_id).
    ids: Mapping[str, str]
    # An assignment is one worker's at a time, and a returned one goes to the next (MTurk).
    exclusive_assignments: bool
    reviews: bool  # it has a review backend of its own, which BAM_REVIEW_BACKEND may name
    released: Released | None  # how a released participant is turned away (None: never)

    def arrival(
        self, params: Mapping[str, str], settings: Settings, own_origin: str | None
    ) -> ArrivalIds | None:
        """The participant's ids from the link's parameters of this platform (at least one is
        given); None for a preview, which creates nothing. 400 for a bad link."""
        ...

    def submit_to(self, c: Connection, ids: ArrivalIds) -> str | None:
        """Where a new participant's completion goes (``participants.submit_to``)."""
        ...

    def fixed_code(self, study: StudyConfig) -> str | None:
        """The study's own completion code on this platform; None: a random code is drawn."""
        ...

    def handing(self, participant: Any, study: StudyConfig, code: str) -> Handing: ...

    def no_consent_code(self, study: StudyConfig) -> str | None:
        """The code a participant who declined consent goes back with (None: no code)."""
        ...

    def incompatible_device_code(self, study: StudyConfig) -> str | None:
        """The code a participant turned away by the device check goes back with (None)."""
        ...

    def withdrawal(self, participant: Any, study: StudyConfig) -> Leaving: ...

    def review_backend(
        self, settings: Settings, db: Database, replica: bool
    ) -> ReviewBackend | None:
        """The backend that reviews this platform's participants: its local replica's, or the
        platform's own; None: it has none."""
        ...

    def awaits_decision(self, participant: Any) -> bool:
        """Whether the participant's work is open to approval or rejection (their flow status
        and the platform's status of their submission)."""
        ...

    def auto_approval_at(self, participant: Any) -> datetime | None:
        """When the platform approves (and pays) the participant's submission by itself if no
        one has decided by then; None: it will not (or not known)."""
        ...

    def check_rejection(self, message: str | None, category: str | None) -> None:
        """422 for a rejection the platform would refuse."""
        ...

    def status_after(self, decision: ReviewDecision) -> str | None:
        """The platform's status of the submission once ``decision`` is taken (None: none)."""
        ...

    def bonus_budget_cents(self, study: StudyConfig) -> int | None:
        """The most the study's bonuses on this platform may come to, in cents of its currency
        (the study file's budget; None: no cap)."""
        ...

    def own_replica_rows(self, participant: Any) -> Rows:
        """The replica rows of the participant's turn alone, children before parents."""
        ...

    def shared_replica_rows(self, participant: Any) -> Rows:
        """The replica rows that name the participant among others."""
        ...


class BasePlatform:
    """A platform's defaults: arrival maps ``ids`` (an id's name -> its URL parameter) onto the
    participant's ids and needs every one of ``parameters``; a random completion code shown on
    the page; no replica, no reviews, no status."""

    name: ClassVar[str]
    display_name: ClassVar[str]
    parameters: ClassVar[Mapping[str, str]] = {}
    # platform_participant_id, platform_submission_id, platform_study_id -> its parameter
    ids: ClassVar[Mapping[str, str]] = {}
    exclusive_assignments: ClassVar[bool] = False
    reviews: ClassVar[bool] = False
    released: ClassVar[Released | None] = None
    done: ClassVar[str] = "Your data has been deleted. You may close this page."

    def arrival(
        self, params: Mapping[str, str], settings: Settings, own_origin: str | None
    ) -> ArrivalIds | None:
        missing = [name for name in self.parameters if params.get(name) is None]
        if missing:
            raise ApiError(400, f"the {self.display_name} link lacks {', '.join(missing)}")
        return ArrivalIds(self.name, **{id_: params[name] for id_, name in self.ids.items()})

    def submit_to(self, c: Connection, ids: ArrivalIds) -> str | None:
        return ids.submit_to

    def fixed_code(self, study: StudyConfig) -> str | None:
        return None

    def handing(self, participant: Any, study: StudyConfig, code: str) -> Handing:
        return Handing()

    def no_consent_code(self, study: StudyConfig) -> str | None:
        return None

    def incompatible_device_code(self, study: StudyConfig) -> str | None:
        return None

    def withdrawal(self, participant: Any, study: StudyConfig) -> Leaving:
        return Leaving(self.done)

    def review_backend(
        self, settings: Settings, db: Database, replica: bool
    ) -> ReviewBackend | None:
        return None

    def awaits_decision(self, participant: Any) -> bool:
        return bool(participant.status == "submitted")

    def auto_approval_at(self, participant: Any) -> datetime | None:
        return None

    def check_rejection(self, message: str | None, category: str | None) -> None:
        return None

    def status_after(self, decision: ReviewDecision) -> str | None:
        return None

    def bonus_budget_cents(self, study: StudyConfig) -> int | None:
        return None

    def own_replica_rows(self, participant: Any) -> Rows:
        return []

    def shared_replica_rows(self, participant: Any) -> Rows:
        return []
