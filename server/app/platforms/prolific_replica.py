"""The local Prolific replica's API: the subset of Prolific's REST API (``/api/v1``) that the
study server's client uses, at the same paths, with the same fields, statuses, status codes
and refusals, keeping its state in the database (``replica_models``).

``handle`` answers one request; the router (``routers/prolific.py``) serves it over HTTP at
``/prolific/api/v1/...``, and ``ReplicaTransport`` hands the client's requests to it inside the
server (the dashboard's reviews on a rehearsal). As on Prolific:

- a study is made as a draft (UNPUBLISHED), refused for the fields Prolific refuses (completion
  codes and their actions, devices, filters, submissions_config, times), and published, paused
  and started with transitions; after publishing its places can only go up, and at most its
  max_concurrent_submissions take part at once;
- submissions are listed for one study (``?study=`` is required), page by page, and counted
  per status (``/studies/{id}/submissions/counts/``);
- a completion code with the REQUEST_RETURN action (our NO_CONSENT code) completes the
  submission (AWAITING REVIEW) with ``return_requested`` set; it is RETURNED only if the
  participant then returns it (``routers/prolific.py``);
- a submission is approved or rejected once it is AWAITING REVIEW (a TIMED-OUT one may be
  approved too); a rejection needs one of Prolific's categories and a message of at least 100
  characters (400 otherwise); the same transition sent again is ignored (the endpoint is
  idempotent);
- bonuses are set up (``csv_bonuses``: participant or submission id, amount in the currency)
  and paid with ``pay``, which is not idempotent: a second ``pay`` pays again; a submission
  lists the bonuses paid on it (``bonus_payments``);
- messages (``POST /messages/``, ``/messages/bulk/``) go only to participants with a
  submission in the study named, are kept, and are listed with ``GET /messages/?user_id=``;
- the one workspace (``Workspace``: its currency, the funds put in it) has a balance that the
  rewards of approved submissions and the bonuses paid take from, with Prolific's fee, and that
  published studies hold their places' cost from; the study cost calculator and the reward
  recommendations answer as Prolific's;
- a draft can be scheduled (SCHEDULE_PUBLISH with a ``publish_at`` in the future; published at
  that time) and a published study's PATCH takes its places, ``internal_name`` and
  ``submissions_config``;
- webhooks: the workspace's one signing secret (``POST /hooks/secrets/``, a new one replaces
  the old; made by the replica itself when it first signs an event), subscriptions made
  disabled with an ``X-Hook-Secret`` that confirms them, and each delivery recorded with its
  status (PENDING, SUCCEEDED, FAILED); with no subscription at all, events go to this server's
  own webhook (``routers/prolific.py``), so a rehearsal needs no setting;
- participant groups: made, listed, joined and left through the API or by a completion code's
  ADD_TO_PARTICIPANT_GROUP / REMOVE_FROM_PARTICIPANT_GROUP, and the study filters
  ``participant_group_blocklist``, ``participant_group_allowlist`` and
  ``previous_studies_blocklist`` keep out whom they name.
"""

from __future__ import annotations

import hashlib
import json
import re
import secrets
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from decimal import Decimal, InvalidOperation
from typing import Any
from urllib.parse import parse_qs

import httpx
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from server.app.config import prolific_least_maximum_minutes
from server.app.platforms.prolific import SUBMISSION_STATUSES
from server.app.platforms.prolific_sync import signature
from server.app.platforms.review import REJECTION_CATEGORIES
from server.app.storage.db import Database
from server.app.storage.models import utcnow
from server.app.storage.replica_models import (
    ProlificReplicaBonusSetup,
    ProlificReplicaGroupMember,
    ProlificReplicaHookEvent,
    ProlificReplicaHookSecret,
    ProlificReplicaMessage,
    ProlificReplicaParticipantGroup,
    ProlificReplicaPayment,
    ProlificReplicaStudy,
    ProlificReplicaSubmission,
    ProlificReplicaSubscription,
)

# Where this server serves the replica (its pages, its API under /api/v1, and the completion
# URL that stands in for app.prolific.com's: /submissions/complete?cc=CODE).
REPLICA_PATH = "/prolific"
STUDY_ACTIONS = {
    "PUBLISH": ({"UNPUBLISHED"}, "ACTIVE"),
    "SCHEDULE_PUBLISH": ({"UNPUBLISHED"}, "SCHEDULED"),
    "CANCEL_PUBLISH": ({"SCHEDULED"}, "UNPUBLISHED"),
    "PAUSE": ({"ACTIVE"}, "PAUSED"),
    "START": ({"PAUSED", "AWAITING REVIEW"}, "ACTIVE"),
    "STOP": ({"ACTIVE", "PAUSED", "AWAITING REVIEW"}, "COMPLETED"),
}
SUBMISSION_ACTIONS = {"APPROVE": "APPROVED", "REJECT": "REJECTED"}
# The statuses each decision is taken from. A TIMED-OUT submission can be approved as well:
# "You will not be charged for this submission, but you can also manually approve them if you
# wish" (researcher-help.prolific.com, "Timed out submission status"), which pays a timed-out
# participant who finished.
DECIDED_FROM = {"APPROVE": ("AWAITING REVIEW", "TIMED-OUT"), "REJECT": ("AWAITING REVIEW",)}
LARGEST_MAXIMUM_MINUTES = 24 * 60 - 1
# A place is held by these; RETURNED, TIMED-OUT and REJECTED give it back.
HOLDING = ("RESERVED", "ACTIVE", "AWAITING REVIEW", "APPROVED")
MIN_REJECTION_MESSAGE = 100
CODE_ACTIONS = (
    "AUTOMATICALLY_APPROVE",
    "MANUALLY_REVIEW",
    "REQUEST_RETURN",
    "ADD_TO_PARTICIPANT_GROUP",
    "REMOVE_FROM_PARTICIPANT_GROUP",
    "DYNAMIC_PAYMENT",
    "FIXED_SCREEN_OUT_PAYMENT",
)
DEVICES = ("desktop", "tablet", "mobile")
# Filters that name participant groups of the workspace.
GROUP_FILTERS = ("participant_group_allowlist", "participant_group_blocklist")
# What a published study's PATCH may change (the API reference's update-study).
PUBLISHED_CHANGES = ("total_available_places", "internal_name", "submissions_config")
# The webhooks' event types (GET /hooks/event-types/).
EVENT_TYPES = (
    "submission.status.change",
    "study.status.change",
    "study.progress.change",
    "study.has_high_return_rate",
)
PLACEHOLDERS = ("{{%PROLIFIC_PID%}}", "{{%STUDY_ID%}}", "{{%SESSION_ID%}}")


# The replica's one workspace and project: every study is made in them; its one researcher
# (the sender of every message).
WORKSPACE_ID = "5e0f000000000000000000a1"
PROJECT_ID = "5e0f000000000000000000b1"
RESEARCHER_ID = "5e0f000000000000000000c1"
# GET /messages/ lists "up to the last 30 days of messages".
MESSAGES_KEPT = timedelta(days=30)
# Prolific's service fee on rewards and bonuses (VAT: none).
SERVICE_FEE = Decimal("0.333")
# Prolific's minimum hourly pay and the pay it recommends, in cents (researcher help).
HOURLY_REWARD = {"GBP": (600, 900), "USD": (800, 1200)}
# A published study holds the cost of its places not yet paid.
PUBLISHED = ("ACTIVE", "PAUSED", "AWAITING REVIEW")


@dataclass(frozen=True)
class StudyChange:
    """A replica study took a new status (Prolific sends ``study.status.change``)."""

    study_id: str
    status: str
    at: datetime


@dataclass(frozen=True)
class Workspace:
    """The replica's workspace: its currency and the funds put in it, in cents."""

    currency: str = "GBP"
    funds: int = 100_000


def workspace_of(settings: Any) -> Workspace:
    """The replica's workspace for the server's settings: BAM_PROLIFIC_CURRENCY, and
    BAM_PROLIFIC_REPLICA_FUNDS put in it."""
    return Workspace(settings.prolific_currency, int(settings.prolific_replica_funds * 100))


def with_fees(cents: int) -> int:
    """What paying ``cents`` to participants costs the workspace (Prolific's fee on top)."""
    return cents + int((cents * SERVICE_FEE).to_integral_value())


class Refusal(Exception):
    def __init__(self, status: int, detail: str) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail


def is_replica_study(s: Session | Any, study_id: str) -> bool:
    """Whether ``study_id`` is a study of this server's replica (``s``: a session or a
    connection)."""
    found = s.execute(select(ProlificReplicaStudy.id).where(ProlificReplicaStudy.id == study_id))
    return found.first() is not None


def completion_url(code: str) -> str:
    """The replica's completion URL, which stands in for Prolific's."""
    return f"{REPLICA_PATH}/submissions/complete?cc={code}"


def new_id() -> str:
    """An id shaped like Prolific's (24 hexadecimal digits)."""
    return secrets.token_hex(12)


def error_body(status: int, detail: str) -> dict[str, Any]:
    titles = {
        400: "Bad request",
        401: "Unauthorized",
        404: "Not found",
        405: "Not allowed",
        429: "Too many requests",
    }
    return {"error": {"status": status, "title": titles.get(status, "Error"), "detail": detail}}


# -- views ------------------------------------------------------------------------------------
def _submissions(s: Session, study_id: str, statuses: tuple[str, ...]) -> int:
    """The study's submissions in one of ``statuses``."""
    count = s.scalar(
        select(func.count())
        .select_from(ProlificReplicaSubmission)
        .where(
            ProlificReplicaSubmission.study_id == study_id,
            ProlificReplicaSubmission.status.in_(statuses),
        )
    )
    return int(count or 0)


def places_taken(s: Session, study_id: str) -> int:
    """The study's places held: a submission approved after it timed out (no completion code
    reached the study) holds none, as on Prolific, where approving it makes the participant an
    extra one."""
    extra = s.scalar(
        select(func.count())
        .select_from(ProlificReplicaSubmission)
        .where(
            ProlificReplicaSubmission.study_id == study_id,
            ProlificReplicaSubmission.status == "APPROVED",
            ProlificReplicaSubmission.study_code.is_(None),
        )
    )
    return _submissions(s, study_id, HOLDING) - int(extra or 0)


def taking_part(s: Session, study_id: str) -> int:
    """Submissions under way (what max_concurrent_submissions caps)."""
    return _submissions(s, study_id, ("RESERVED", "ACTIVE"))


def concurrency_limit(study: ProlificReplicaStudy) -> int | None:
    """The study's max_concurrent_submissions; None: no limit (-1 or not given)."""
    config = study.fields.get("submissions_config") or {}
    limit = config.get("max_concurrent_submissions", -1) if isinstance(config, dict) else -1
    return limit if isinstance(limit, int) and limit >= 1 else None


def study_view(s: Session, study: ProlificReplicaStudy) -> dict[str, Any]:
    return {
        **study.fields,
        "project": PROJECT_ID,  # the replica's one project (studies made before it had none)
        "id": study.id,
        "name": study.name,
        "status": study.status,
        "external_study_url": study.external_study_url,
        "total_available_places": study.total_available_places,
        "places_taken": places_taken(s, study.id),
        "reward": study.reward,
        "maximum_allowed_time": study.maximum_allowed_time,
        "date_created": study.created_at.isoformat(),
        "published_at": study.published_at.isoformat() if study.published_at else None,
    }


def submission_view(row: ProlificReplicaSubmission) -> dict[str, Any]:
    return {
        "id": row.id,
        "study_id": row.study_id,
        "participant_id": row.participant_id,
        "status": row.status,
        "started_at": row.started_at.isoformat(),
        "completed_at": row.completed_at.isoformat() if row.completed_at else None,
        "study_code": row.study_code,
        "return_requested": row.return_requested.isoformat() if row.return_requested else None,
    }


def submission_detail(s: Session, row: ProlificReplicaSubmission) -> dict[str, Any]:
    """``GET /submissions/{id}/``: the submission with its ``bonus_payments``, the bonuses paid
    on it in cents (each ``pay`` of a set-up that names its participant or it), as Prolific's
    SubmissionDetail lists them."""
    paid = s.scalars(
        select(ProlificReplicaPayment.amount)
        .join(
            ProlificReplicaBonusSetup,
            ProlificReplicaBonusSetup.id == ProlificReplicaPayment.setup_id,
        )
        .where(
            ProlificReplicaBonusSetup.study_id == row.study_id,
            ProlificReplicaPayment.participant_id == row.participant_id,
        )
        .order_by(ProlificReplicaPayment.id)
    ).all()
    return {**submission_view(row), "bonus_payments": list(paid)}


# -- the API ----------------------------------------------------------------------------------
def _study(s: Session, study_id: str) -> ProlificReplicaStudy:
    study = s.get(ProlificReplicaStudy, study_id)
    if study is None:
        raise Refusal(404, f"Study {study_id} not found.")
    return study


def _submission(s: Session, submission_id: str) -> ProlificReplicaSubmission:
    row = s.get(ProlificReplicaSubmission, submission_id)
    if row is None:
        raise Refusal(404, f"Submission {submission_id} not found.")
    return row


def _positive_int(body: dict[str, Any], name: str) -> int:
    value = body.get(name)
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise Refusal(400, f"{name}: a positive whole number is required.")
    return value


def _check_completion_codes(codes: Any) -> None:
    if not isinstance(codes, list) or not codes:
        raise Refusal(400, "completion_codes: at least one completion code is required.")
    seen: set[str] = set()
    for code in codes:
        if not isinstance(code, dict) or not code.get("code") or not code.get("code_type"):
            raise Refusal(400, "completion_codes: each needs a code and a code_type.")
        if not isinstance(code["code"], str) or code["code"] in seen:
            raise Refusal(400, f"completion_codes: {code['code']!r} is given twice.")
        seen.add(code["code"])
        if code.get("actor", "participant") not in ("participant", "researcher"):
            raise Refusal(400, "completion_codes: actor is participant or researcher.")
        actions = code.get("actions", [])
        if not isinstance(actions, list) or not all(isinstance(a, dict) for a in actions):
            raise Refusal(400, "completion_codes: actions is a list of objects.")
        names = [a.get("action") for a in actions]
        for action in actions:
            if action.get("action") not in CODE_ACTIONS:
                raise Refusal(400, f"completion_codes: action is one of {', '.join(CODE_ACTIONS)}.")
            reason = action.get("return_reason")
            if action["action"] == "REQUEST_RETURN" and not (
                isinstance(reason, str) and reason.strip()
            ):
                raise Refusal(400, "completion_codes: REQUEST_RETURN needs a return_reason.")
        if "MANUALLY_REVIEW" in names and "AUTOMATICALLY_APPROVE" in names:
            raise Refusal(
                400, "completion_codes: MANUALLY_REVIEW cannot go with AUTOMATICALLY_APPROVE."
            )


def _check_devices(devices: Any) -> None:
    if not isinstance(devices, list) or not set(devices) <= set(DEVICES):
        raise Refusal(400, f"device_compatibility: a list of {', '.join(DEVICES)}.")


def _check_filters(filters: Any) -> None:
    if not isinstance(filters, list):
        raise Refusal(400, "filters: a list of filters.")
    for item in filters:
        if not isinstance(item, dict) or not isinstance(item.get("filter_id"), str):
            raise Refusal(400, "filters: each filter needs a filter_id.")
        values = item.get("selected_values")
        if values is not None and (
            not isinstance(values, list) or not all(isinstance(v, str) for v in values)
        ):
            raise Refusal(400, f"filters: {item['filter_id']}: selected_values is a list.")
        if item["filter_id"] == "previous_studies_blocklist":
            if not values or not all(re.fullmatch(r"[0-9a-f]{24}", v) for v in values):
                raise Refusal(
                    400, "filters: previous_studies_blocklist: selected_values are study ids."
                )
        if item["filter_id"] in GROUP_FILTERS:
            if not values or not all(re.fullmatch(r"[0-9a-f]{24}", v) for v in values):
                raise Refusal(
                    400, f"filters: {item['filter_id']}: selected_values are participant group ids."
                )


def _check_groups(s: Session, body: dict[str, Any]) -> None:
    """Each participant group the study names (its group filters, its codes' group actions) is
    a group of the workspace, not deleted."""
    named = [
        v
        for item in body.get("filters", [])
        if item["filter_id"] in GROUP_FILTERS
        for v in item["selected_values"]
    ]
    for code in body.get("completion_codes", []):
        for action in code.get("actions", []):
            if action["action"] in ("ADD_TO_PARTICIPANT_GROUP", "REMOVE_FROM_PARTICIPANT_GROUP"):
                group = action.get("participant_group")
                if not isinstance(group, str) or not group:
                    raise Refusal(
                        400, f"completion_codes: {action['action']} needs a participant_group."
                    )
                named.append(group)
    for group_id in named:
        row = s.get(ProlificReplicaParticipantGroup, group_id)
        if row is None or row.is_deleted:
            raise Refusal(400, f"Participant group {group_id} not found in your workspace.")


def _check_submissions_config(config: Any) -> None:
    if not isinstance(config, dict):
        raise Refusal(400, "submissions_config: an object.")
    for name in ("max_concurrent_submissions", "max_submissions_per_participant"):
        value = config.get(name, -1)
        if isinstance(value, bool) or not isinstance(value, int) or not (value == -1 or value >= 1):
            raise Refusal(400, f"submissions_config: {name} is -1 (no limit) or at least 1.")


def create_study(s: Session, body: dict[str, Any]) -> tuple[int, Any]:
    name = body.get("name")
    if not isinstance(name, str) or not name.strip():
        raise Refusal(400, "name: This field is required.")
    url = body.get("external_study_url")
    if not isinstance(url, str) or not url.startswith(("https://", "http://")):
        raise Refusal(400, "external_study_url: Enter a valid URL.")
    if body.get("prolific_id_option") not in ("url_parameters", "question", "not_required"):
        raise Refusal(400, "prolific_id_option: url_parameters, question or not_required.")
    description = body.get("description")
    if not isinstance(description, str) or not description.strip():
        raise Refusal(400, "description: This field is required.")
    _check_completion_codes(body.get("completion_codes"))
    _check_devices(body.get("device_compatibility", []))
    _check_filters(body.get("filters", []))
    _check_submissions_config(body.get("submissions_config", {}))
    places = _positive_int(body, "total_available_places")
    reward = _positive_int(body, "reward")
    estimated = _positive_int(body, "estimated_completion_time")
    # Left out, Prolific sets the largest value ("the max value": under 24 hours).
    maximum = body.get("maximum_allowed_time", LARGEST_MAXIMUM_MINUTES)
    least = prolific_least_maximum_minutes(estimated)
    if not isinstance(maximum, int) or isinstance(maximum, bool) or maximum >= 24 * 60:
        raise Refusal(400, "maximum_allowed_time: whole minutes, under 24 hours.")
    if maximum < least:
        raise Refusal(
            400,
            f"maximum_allowed_time: at least {least} minutes for an estimated completion time "
            f"of {estimated} (two minutes plus two times the estimated time plus two times its "
            "square root).",
        )
    _check_groups(s, body)
    if body.get("project", PROJECT_ID) != PROJECT_ID:
        raise Refusal(400, f"project: no project {body.get('project')!r} in your workspace.")
    body = {**body, "project": PROJECT_ID}
    study = ProlificReplicaStudy(
        id=new_id(),
        name=name,
        status="UNPUBLISHED",
        external_study_url=url,
        total_available_places=places,
        reward=reward,
        maximum_allowed_time=maximum,
        fields={k: v for k, v in body.items() if k not in ("id", "status")},
        created_at=utcnow(),
    )
    s.add(study)
    s.flush()
    return 201, study_view(s, study)


def balance(s: Session, workspace: Workspace) -> dict[str, Any]:
    """``GET /workspaces/{id}/balance/``: the funds less what was paid (the rewards of approved
    submissions and the bonuses, each with Prolific's fee), and, available, less what the
    published studies hold for their places not yet paid."""
    approved = s.execute(
        select(ProlificReplicaStudy.reward, func.count())
        .join(
            ProlificReplicaSubmission, ProlificReplicaSubmission.study_id == ProlificReplicaStudy.id
        )
        .where(ProlificReplicaSubmission.status == "APPROVED")
        .group_by(ProlificReplicaStudy.id, ProlificReplicaStudy.reward)
    ).all()
    rewards = sum(reward * count for reward, count in approved)
    bonuses = int(s.scalar(select(func.coalesce(func.sum(ProlificReplicaPayment.amount), 0))) or 0)
    total = workspace.funds - with_fees(rewards) - with_fees(bonuses)
    held = 0
    for study in s.scalars(
        select(ProlificReplicaStudy).where(ProlificReplicaStudy.status.in_(PUBLISHED))
    ):
        paid = _submissions(s, study.id, ("APPROVED",))
        held += with_fees(max(study.total_available_places - paid, 0) * study.reward)
    return {
        "currency_code": workspace.currency,
        "total_balance": total,
        "available_balance": total - held,
    }


def study_cost(body: dict[str, Any]) -> tuple[int, Any]:
    """``POST /study-cost-calculator/``: the reward of every place, with Prolific's fee."""
    values = [body.get(name) for name in ("reward", "total_available_places")]
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0 for v in values):
        raise Refusal(400, "reward and total_available_places: positive numbers are required.")
    reward, places = values
    return 200, {"total_cost": with_fees(round(reward * places))}  # type: ignore[operator]


def reward_recommendations(query: dict[str, str]) -> tuple[int, Any]:
    if query.get("workspace_id") != WORKSPACE_ID:
        raise Refusal(400, "workspace_id: the id of your workspace is required.")
    currency = query.get("currency")
    if currency not in HOURLY_REWARD:
        raise Refusal(400, "currency: one of GBP, USD.")
    least, good = HOURLY_REWARD[currency]
    return 200, [
        {"currency": currency, "min_reward_per_hour": least, "recommended_reward_per_hour": good}
    ]


def update_study(s: Session, study_id: str, body: dict[str, Any]) -> tuple[int, Any]:
    """``PATCH /studies/{id}/``: a published study takes its places (only up), its internal
    name and its ``submissions_config`` (the concurrency, as the API reference's update-study
    allows); a draft those and its scheduled ``publish_at``."""
    study = _study(s, study_id)
    allowed = PUBLISHED_CHANGES + (("publish_at",) if study.status == "UNPUBLISHED" else ())
    if not body or set(body) - set(allowed):
        raise Refusal(400, f"Only {', '.join(allowed)} can be changed here.")
    if "submissions_config" in body:
        _check_submissions_config(body["submissions_config"])
        config = study.fields.get("submissions_config") or {}
        study.fields = {
            **study.fields,
            "submissions_config": {**config, **body["submissions_config"]},
        }
    if "internal_name" in body:
        if not isinstance(body["internal_name"], str):
            raise Refusal(400, "internal_name: a string.")
        study.fields = {**study.fields, "internal_name": body["internal_name"]}
    if "publish_at" in body:
        study.fields = {**study.fields, "publish_at": _publish_at(body["publish_at"])}
    if "total_available_places" in body:
        places = _positive_int(body, "total_available_places")
        if study.status != "UNPUBLISHED" and places < study.total_available_places:
            raise Refusal(400, "total_available_places: a published study's places can only go up.")
        study.total_available_places = places
        # As Prolific: more places reopen a full study, and "a completed study will become
        # active again".
        if study.status in ("AWAITING REVIEW", "COMPLETED") and places > places_taken(s, study.id):
            study.status = "ACTIVE"
    return 200, study_view(s, study)


def _publish_at(value: Any) -> str:
    """A scheduled publication's time: ISO 8601, in the future."""
    try:
        moment = datetime.fromisoformat(str(value).replace("Z", "+00:00"))
    except ValueError:
        raise Refusal(400, "publish_at: an ISO 8601 date and time.") from None
    if moment.tzinfo is None:
        moment = moment.replace(tzinfo=UTC)
    if moment <= utcnow():
        raise Refusal(400, "publish_at: a time in the future.")
    return moment.astimezone(UTC).isoformat()


def transition_study(s: Session, study_id: str, body: dict[str, Any]) -> tuple[int, Any]:
    study = _study(s, study_id)
    action = body.get("action")
    if action not in STUDY_ACTIONS:
        raise Refusal(400, f"action: one of {', '.join(STUDY_ACTIONS)}.")
    sources, target = STUDY_ACTIONS[action]
    if study.status not in sources:
        raise Refusal(400, f"A study that is {study.status} cannot {action}.")
    if action == "SCHEDULE_PUBLISH":
        # "A publish_at field must be set either on the study or provided in this request."
        given = body.get("publish_at") or study.fields.get("publish_at")
        if not given:
            raise Refusal(400, "publish_at: required to SCHEDULE_PUBLISH a study.")
        study.fields = {**study.fields, "publish_at": _publish_at(given)}
    study.status = target
    if action == "PUBLISH":
        study.published_at = utcnow()
    return 200, study_view(s, study)


def publish_due(s: Session) -> list[StudyChange]:
    """Scheduled studies whose ``publish_at`` has come are published (ACTIVE) at that time; the
    changes, for their ``study.status.change``."""
    now = utcnow()
    changes = []
    for study in s.scalars(
        select(ProlificReplicaStudy).where(ProlificReplicaStudy.status == "SCHEDULED")
    ):
        at = datetime.fromisoformat(str(study.fields.get("publish_at")))
        if at <= now:
            study.status, study.published_at = "ACTIVE", at
            changes.append(StudyChange(study.id, "ACTIVE", at))
    return changes


def list_submissions(s: Session, query: dict[str, str]) -> tuple[int, Any]:
    study_id = query.get("study")
    if not study_id:
        raise Refusal(400, "study: a study id is required to list submissions.")
    _study(s, study_id)
    try:
        page = int(query.get("page", "1"))
        size = int(query.get("page_size", "20"))
    except ValueError:
        raise Refusal(400, "page and page_size are whole numbers.") from None
    if page < 1 or not 1 <= size <= 200:
        raise Refusal(400, "page from 1, page_size from 1 to 200.")
    where = [ProlificReplicaSubmission.study_id == study_id]
    if query.get("status"):
        # The filter spells statuses with underscores (AWAITING_REVIEW), as Prolific's does.
        spelt = {name.replace(" ", "_").replace("-", "_"): name for name in SUBMISSION_STATUSES}
        status = spelt.get(query["status"], query["status"])
        where.append(ProlificReplicaSubmission.status == status)
    newest_first = query.get("ordering") == "-started_at"  # else by started_at
    total = int(
        s.scalar(select(func.count()).select_from(ProlificReplicaSubmission).where(*where)) or 0
    )
    rows = s.scalars(
        select(ProlificReplicaSubmission)
        .where(*where)
        .order_by(
            *(
                (ProlificReplicaSubmission.started_at.desc(), ProlificReplicaSubmission.id.desc())
                if newest_first
                else (ProlificReplicaSubmission.started_at, ProlificReplicaSubmission.id)
            )
        )
        .offset((page - 1) * size)
        .limit(size)
    ).all()
    following = None
    if page * size < total:
        kept = "".join(f"&{k}={query[k]}" for k in ("status", "ordering") if query.get(k))
        following = {
            "href": f"submissions/?study={study_id}&page={page + 1}&page_size={size}{kept}"
        }
    return 200, {
        "results": [submission_view(r) for r in rows],
        "_links": {"next": following},
        "meta": {"count": total},
    }


# The statuses ``GET /studies/{id}/submissions/counts/`` counts (its SubmissionsCountResponse).
COUNTED_STATUSES = (
    "ACTIVE",
    "APPROVED",
    "AWAITING REVIEW",
    "REJECTED",
    "RESERVED",
    "RETURNED",
    "TIMED-OUT",
    "PARTIALLY APPROVED",
    "SCREENED OUT",
)


def submission_counts(s: Session, study_id: str) -> tuple[int, Any]:
    """``GET /studies/{id}/submissions/counts/``: the study's submissions per status (each of
    Prolific's, 0 where none) and their ``TOTAL``."""
    _study(s, study_id)
    counted = dict(
        s.execute(
            select(ProlificReplicaSubmission.status, func.count())
            .where(ProlificReplicaSubmission.study_id == study_id)
            .group_by(ProlificReplicaSubmission.status)
        ).all()
    )
    counts = {status: int(counted.get(status, 0)) for status in COUNTED_STATUSES}
    return 200, {**counts, "TOTAL": int(sum(counted.values()))}


def transition_submission(s: Session, submission_id: str, body: dict[str, Any]) -> tuple[int, Any]:
    row = _submission(s, submission_id)
    action = body.get("action")
    if action not in SUBMISSION_ACTIONS:
        raise Refusal(400, f"action: one of {', '.join(SUBMISSION_ACTIONS)}.")
    target = SUBMISSION_ACTIONS[action]
    if action == "REJECT":
        message = body.get("message")
        if not isinstance(message, str) or len(message) < MIN_REJECTION_MESSAGE:
            raise Refusal(400, "message: a rejection message is at least 100 characters long.")
        if body.get("rejection_category") not in REJECTION_CATEGORIES:
            raise Refusal(400, f"rejection_category: one of {', '.join(REJECTION_CATEGORIES)}.")
    if row.status == target:  # idempotent: the same request again is ignored
        return 200, submission_view(row)
    if row.status not in DECIDED_FROM[action]:
        raise Refusal(400, f"A submission that is {row.status} cannot be {target.lower()}.")
    row.status = target
    row.reviewed_at = utcnow()
    if action == "REJECT":
        row.message = body["message"]
        row.rejection_category = body["rejection_category"]
    return 200, submission_view(row)


def requests_return(code: dict[str, Any]) -> bool:
    """Whether a completion code (one of the study's ``completion_codes``) asks the participant
    to return the submission (its actions include REQUEST_RETURN, as our NO_CONSENT code's)."""
    actions = code.get("actions") or []
    return any(isinstance(a, dict) and a.get("action") == "REQUEST_RETURN" for a in actions)


def return_reason(code: dict[str, Any]) -> str:
    """The return reason of the code's REQUEST_RETURN action ('' without one)."""
    actions = code.get("actions") or []
    for action in actions:
        if isinstance(action, dict) and action.get("action") == "REQUEST_RETURN":
            return str(action.get("return_reason") or "")
    return ""


def bulk_approve(s: Session, body: dict[str, Any]) -> tuple[int, Any]:
    ids = body.get("submission_ids")
    if not isinstance(ids, list) or not ids or not all(isinstance(i, str) for i in ids):
        raise Refusal(400, "submission_ids: a list of submission ids is required.")
    rows = [_submission(s, i) for i in ids]
    for row in rows:
        if row.status not in ("AWAITING REVIEW", "APPROVED"):
            raise Refusal(400, f"Submission {row.id} is {row.status}: it cannot be approved.")
    for row in rows:
        if row.status != "APPROVED":
            row.status = "APPROVED"
            row.reviewed_at = utcnow()
    return 200, "The request to bulk approve has been made successfully."


def _cents(text: str) -> int:
    if not re.fullmatch(r"[0-9]+(\.[0-9]{1,2})?", text):
        raise Refusal(400, f"csv_bonuses: {text!r} is not an amount.")
    try:
        return int(Decimal(text) * 100)
    except InvalidOperation:  # pragma: no cover - the pattern above
        raise Refusal(400, f"csv_bonuses: {text!r} is not an amount.") from None


def set_up_bonuses(s: Session, body: dict[str, Any]) -> tuple[int, Any]:
    study_id = body.get("study_id")
    csv = body.get("csv_bonuses")
    if not isinstance(study_id, str) or not isinstance(csv, str) or not csv.strip():
        raise Refusal(400, "study_id and csv_bonuses are required.")
    _study(s, study_id)
    total = 0
    for line in csv.strip().splitlines():
        who, _, amount = line.partition(",")
        cents = _cents(amount.strip())
        if cents <= 0:
            raise Refusal(400, f"csv_bonuses: the amount for {who} must be more than 0.")
        taken = s.scalar(
            select(ProlificReplicaSubmission).where(
                ProlificReplicaSubmission.study_id == study_id,
                (ProlificReplicaSubmission.participant_id == who.strip())
                | (ProlificReplicaSubmission.id == who.strip()),
            )
        )
        if taken is None:
            raise Refusal(400, f"csv_bonuses: {who.strip()} did not take part in this study.")
        total += cents
    setup = ProlificReplicaBonusSetup(
        id=new_id(), study_id=study_id, csv_bonuses=csv, amount=total, created_at=utcnow()
    )
    s.add(setup)
    fees = with_fees(total) - total
    return 201, {
        "id": setup.id,
        "study": study_id,
        "amount": total,
        "fees": fees,
        "vat": 0,
        "total_amount": total + fees,
    }


def pay_bonuses(s: Session, setup_id: str) -> tuple[int, Any]:
    setup = s.get(ProlificReplicaBonusSetup, setup_id)
    if setup is None:
        raise Refusal(404, f"Bulk bonus payment {setup_id} not found.")
    now = utcnow()
    for line in setup.csv_bonuses.strip().splitlines():
        who, _, amount = line.partition(",")
        participant = who.strip()
        submission = s.get(ProlificReplicaSubmission, participant)
        if submission is not None:
            participant = submission.participant_id
        s.add(
            ProlificReplicaPayment(
                setup_id=setup.id,
                participant_id=participant,
                amount=_cents(amount.strip()),
                paid_at=now,
            )
        )
    return 202, None


# -- messages ---------------------------------------------------------------------------------
def _message_text(body: dict[str, Any]) -> str:
    text = body.get("body")
    if not isinstance(text, str) or not text.strip():
        raise Refusal(400, "body: This field may not be blank.")
    return text


def _recipients(s: Session, study_id: Any, ids: list[Any]) -> list[str]:
    """The recipients, each a participant with a submission in the study (Prolific lets a
    researcher message only those who took part in their studies), or a refusal naming the
    first who is not."""
    if not isinstance(study_id, str) or not study_id:
        raise Refusal(400, "study_id: This field is required.")
    _study(s, study_id)
    if not ids or not all(isinstance(i, str) and i for i in ids):
        raise Refusal(400, "recipient ids: a participant id is required.")
    taken = set(
        s.scalars(
            select(ProlificReplicaSubmission.participant_id).where(
                ProlificReplicaSubmission.study_id == study_id,
                ProlificReplicaSubmission.participant_id.in_(ids),
            )
        )
    )
    for who in ids:
        if who not in taken:
            raise Refusal(
                400,
                f"Participant {who} has no submission in study {study_id}: you can message "
                "only participants who took part in your studies.",
            )
    return list(dict.fromkeys(ids))


def _send(s: Session, study_id: str, recipients: list[str], text: str) -> tuple[int, Any]:
    now = utcnow()
    for who in recipients:
        s.add(
            ProlificReplicaMessage(
                id=new_id(),
                sender_id=RESEARCHER_ID,
                recipient_id=who,
                study_id=study_id,
                body=text,
                sent_at=now,
            )
        )
    return 204, None


def send_message(s: Session, body: dict[str, Any]) -> tuple[int, Any]:
    """``POST /messages/`` ``{recipient_id, body, study_id}``: 204, the message sent."""
    text = _message_text(body)
    recipients = _recipients(s, body.get("study_id"), [body.get("recipient_id")])
    return _send(s, body["study_id"], recipients, text)


def bulk_message(s: Session, body: dict[str, Any]) -> tuple[int, Any]:
    """``POST /messages/bulk/`` ``{ids, body, study_id}``: 204, sent to every one of them, or
    refused (400) and sent to none."""
    text = _message_text(body)
    ids = body.get("ids")
    if not isinstance(ids, list):
        raise Refusal(400, "ids: a list of participant ids is required.")
    recipients = _recipients(s, body.get("study_id"), ids)
    return _send(s, body["study_id"], recipients, text)


def message_view(row: ProlificReplicaMessage) -> dict[str, Any]:
    channel = hashlib.sha256(f"{row.sender_id}:{row.recipient_id}".encode()).hexdigest()[:24]
    return {
        "id": row.id,
        "sender_id": row.sender_id,
        "body": row.body,
        "sent_at": row.sent_at.isoformat(),
        "type": "message",
        "channel_id": channel,
        "data": {"study_id": row.study_id},
    }


def list_messages(s: Session, query: dict[str, str]) -> tuple[int, Any]:
    """``GET /messages/?user_id=`` (the messages with that participant) or ``?created_after=``
    (all messages since then), of the last 30 days, oldest first."""
    since = utcnow() - MESSAGES_KEPT
    where = [ProlificReplicaMessage.sent_at >= since]
    if query.get("user_id"):
        where.append(ProlificReplicaMessage.recipient_id == query["user_id"])
    elif query.get("created_after"):
        try:
            after = datetime.fromisoformat(query["created_after"].replace("Z", "+00:00"))
        except ValueError:
            raise Refusal(400, "created_after: a date and time in ISO 8601.") from None
        if after.tzinfo is None:
            after = after.replace(tzinfo=since.tzinfo)
        where.append(ProlificReplicaMessage.sent_at > after)
    else:
        raise Refusal(400, "user_id or created_after is required.")
    rows = s.scalars(
        select(ProlificReplicaMessage)
        .where(*where)
        .order_by(ProlificReplicaMessage.sent_at, ProlificReplicaMessage.id)
    ).all()
    return 200, {"results": [message_view(row) for row in rows]}


# -- webhooks ---------------------------------------------------------------------------------
def _workspace_id(value: Any) -> str:
    if value != WORKSPACE_ID:
        raise Refusal(400, f"workspace_id: {value!r} is not a workspace of yours.")
    return WORKSPACE_ID


def hook_secret(s: Session, make: bool = False) -> str | None:
    """The workspace's signing secret; with ``make``, one is made when it has none (the
    replica signs its webhooks with it, so that they need no setting)."""
    row = s.scalar(
        select(ProlificReplicaHookSecret).where(
            ProlificReplicaHookSecret.workspace_id == WORKSPACE_ID
        )
    )
    if row is None and make:
        row = ProlificReplicaHookSecret(
            id=new_id(),
            workspace_id=WORKSPACE_ID,
            value=secrets.token_urlsafe(32),
            created_at=utcnow(),
        )
        s.add(row)
        s.flush()
    return row.value if row is not None else None


def _secret_view(row: ProlificReplicaHookSecret) -> dict[str, Any]:
    return {"id": row.id, "value": row.value, "workspace_id": row.workspace_id}


def create_secret(s: Session, body: dict[str, Any]) -> tuple[int, Any]:
    """``POST /hooks/secrets/``: a new secret for the workspace, which replaces the old one."""
    workspace = _workspace_id(body.get("workspace_id"))
    for old in s.scalars(
        select(ProlificReplicaHookSecret).where(ProlificReplicaHookSecret.workspace_id == workspace)
    ):
        s.delete(old)
    s.flush()
    row = ProlificReplicaHookSecret(
        id=new_id(), workspace_id=workspace, value=secrets.token_urlsafe(32), created_at=utcnow()
    )
    s.add(row)
    return 201, _secret_view(row)


def list_secrets(s: Session, query: dict[str, str]) -> tuple[int, Any]:
    workspace = _workspace_id(query.get("workspace_id"))
    rows = s.scalars(
        select(ProlificReplicaHookSecret).where(ProlificReplicaHookSecret.workspace_id == workspace)
    ).all()
    return 200, {"results": [_secret_view(row) for row in rows]}


def subscription_view(row: ProlificReplicaSubscription) -> dict[str, Any]:
    return {
        "id": row.id,
        "event_type": row.event_type,
        "target_url": row.target_url,
        "is_enabled": row.is_enabled,
        "workspace_id": row.workspace_id,
    }


def _subscription(s: Session, subscription_id: str) -> ProlificReplicaSubscription:
    row = s.get(ProlificReplicaSubscription, subscription_id)
    if row is None:
        raise Refusal(404, f"Subscription {subscription_id} not found.")
    return row


def create_subscription(
    s: Session, body: dict[str, Any], headers: dict[str, str] | None
) -> tuple[int, Any]:
    """``POST /hooks/subscriptions/``: made disabled, its ``X-Hook-Secret`` in the answer's
    headers; it delivers once confirmed with that secret. The workspace needs a signing secret
    first, as on Prolific."""
    workspace = _workspace_id(body.get("workspace_id"))
    event_type = body.get("event_type")
    if event_type not in EVENT_TYPES:
        raise Refusal(400, f"event_type: one of {', '.join(EVENT_TYPES)}.")
    url = body.get("target_url")
    if not isinstance(url, str) or not url.startswith(("https://", "http://")):
        raise Refusal(400, "target_url: Enter a valid URL.")
    if hook_secret(s) is None:
        raise Refusal(
            400, "Create a secret for your workspace (POST /hooks/secrets/) before subscribing."
        )
    row = ProlificReplicaSubscription(
        id=new_id(),
        workspace_id=workspace,
        event_type=event_type,
        target_url=url,
        confirmation=secrets.token_hex(32),
        is_enabled=False,
        created_at=utcnow(),
    )
    s.add(row)
    if headers is not None:
        headers["X-Hook-Secret"] = row.confirmation
    return 201, {"results": [subscription_view(row)]}


def confirm_subscription(s: Session, subscription_id: str, body: dict[str, Any]) -> tuple[int, Any]:
    """``POST /hooks/subscriptions/{id}/`` ``{secret}``: the ``X-Hook-Secret`` of its creation
    enables it; another secret is refused."""
    row = _subscription(s, subscription_id)
    given = body.get("secret")
    if not isinstance(given, str) or not secrets.compare_digest(
        given.encode(), row.confirmation.encode()
    ):
        raise Refusal(400, "secret: not the X-Hook-Secret this subscription was created with.")
    row.is_enabled = True
    return 200, subscription_view(row)


def list_subscriptions(s: Session, query: dict[str, str]) -> tuple[int, Any]:
    """``GET /hooks/subscriptions/``: the enabled ones (``is_enabled=false``: the others)."""
    enabled = query.get("is_enabled", "true") != "false"
    where: list[Any] = [ProlificReplicaSubscription.is_enabled.is_(enabled)]
    if query.get("workspace_id"):
        where.append(ProlificReplicaSubscription.workspace_id == query["workspace_id"])
    rows = s.scalars(
        select(ProlificReplicaSubscription)
        .where(*where)
        .order_by(ProlificReplicaSubscription.created_at, ProlificReplicaSubscription.id)
    ).all()
    return 200, {"results": [subscription_view(row) for row in rows]}


def event_view(row: ProlificReplicaHookEvent) -> dict[str, Any]:
    return {
        "id": row.id,
        "datetime_created": row.created_at.isoformat(),
        "datetime_updated": row.updated_at.isoformat(),
        "event_type": row.event_type,
        "resource_id": row.resource_id,
        "status": row.status,
        "target_url": row.target_url,
        "payload": row.payload,
    }


def subscription_events(s: Session, subscription_id: str, query: dict[str, str]) -> tuple[int, Any]:
    """``GET /hooks/subscriptions/{id}/events/``: its deliveries, oldest first."""
    _subscription(s, subscription_id)
    try:
        offset, limit = int(query.get("offset", "0")), int(query.get("limit", "100"))
    except ValueError:
        raise Refusal(400, "offset and limit are whole numbers.") from None
    where = [ProlificReplicaHookEvent.subscription_id == subscription_id]
    if query.get("status"):
        where.append(ProlificReplicaHookEvent.status == query["status"])
    if query.get("resource_id"):
        where.append(ProlificReplicaHookEvent.resource_id == query["resource_id"])
    rows = s.scalars(
        select(ProlificReplicaHookEvent)
        .where(*where)
        .order_by(ProlificReplicaHookEvent.created_at, ProlificReplicaHookEvent.id)
        .offset(max(offset, 0))
        .limit(max(min(limit, 1000), 1))
    ).all()
    return 200, {"results": [event_view(row) for row in rows]}


@dataclass(frozen=True)
class Delivery:
    """One webhook to send: where, the body, and the event row that records it (None: the
    replica's own server, with no subscription)."""

    target_url: str
    payload: dict[str, Any]
    event_id: str | None


def deliveries(
    s: Session, event_type: str, resource_id: str, payload: dict[str, Any], own_url: str
) -> list[Delivery]:
    """Where the event goes: each enabled subscription to its type (its delivery recorded,
    PENDING), or, with none at all in the workspace, this server's own webhook, so that a
    rehearsal needs no subscription and no setting."""
    subscribed = s.scalars(
        select(ProlificReplicaSubscription).where(ProlificReplicaSubscription.is_enabled.is_(True))
    ).all()
    if not subscribed:
        return [Delivery(own_url, payload, None)]
    sent = []
    now = utcnow()
    for row in subscribed:
        if row.event_type != event_type:
            continue
        event = ProlificReplicaHookEvent(
            id=new_id(),
            subscription_id=row.id,
            event_type=event_type,
            resource_id=resource_id,
            status="PENDING",
            target_url=row.target_url,
            payload=payload,
            created_at=now,
            updated_at=now,
        )
        s.add(event)
        sent.append(Delivery(row.target_url, payload, event.id))
    return sent


def delivered(db: Database, event_id: str | None, succeeded: bool) -> None:
    """Record how the target answered a delivery (SUCCEEDED: 2xx)."""
    if event_id is None:
        return
    with db.write() as s:
        row = s.get(ProlificReplicaHookEvent, event_id)
        if row is not None:
            row.status = "SUCCEEDED" if succeeded else "FAILED"
            row.updated_at = utcnow()


# -- participant groups -----------------------------------------------------------------------
def _group(s: Session, group_id: str) -> ProlificReplicaParticipantGroup:
    row = s.get(ProlificReplicaParticipantGroup, group_id)
    if row is None or row.is_deleted:
        raise Refusal(404, f"Participant group {group_id} not found.")
    return row


def _members(s: Session, group_id: str) -> list[ProlificReplicaGroupMember]:
    return list(
        s.scalars(
            select(ProlificReplicaGroupMember)
            .where(ProlificReplicaGroupMember.group_id == group_id)
            .order_by(
                ProlificReplicaGroupMember.created_at, ProlificReplicaGroupMember.participant_id
            )
        )
    )


def group_view(s: Session, row: ProlificReplicaParticipantGroup) -> dict[str, Any]:
    feeders = [
        {"id": study.id, "name": study.name}
        for study in s.scalars(select(ProlificReplicaStudy).order_by(ProlificReplicaStudy.id))
        if row.id in _code_groups(study.fields)
    ]
    return {
        "id": row.id,
        "name": row.name,
        "project_id": None,
        "workspace_id": row.workspace_id,
        "organisation_id": None,
        "description": row.description,
        "participant_count": len(_members(s, row.id)),
        "is_deleted": row.is_deleted,
        "feeder_studies": feeders,
    }


def _code_groups(fields: dict[str, Any]) -> set[str]:
    """The groups the study's completion codes add to or remove from."""
    return {
        str(action.get("participant_group"))
        for code in fields.get("completion_codes") or []
        for action in code.get("actions") or []
        if isinstance(action, dict)
        and action.get("action") in ("ADD_TO_PARTICIPANT_GROUP", "REMOVE_FROM_PARTICIPANT_GROUP")
    }


def _participant_ids(body: dict[str, Any], name: str = "participant_ids") -> list[str]:
    ids = body.get(name, [])
    if not isinstance(ids, list) or not all(
        isinstance(i, str) and re.fullmatch(r"[0-9a-f]{24}", i) for i in ids
    ):
        raise Refusal(400, f"{name}: a list of participant ids.")
    return list(dict.fromkeys(ids))


def add_members(s: Session, group_id: str, participant_ids: list[str]) -> None:
    """Add participants who are not members yet (members already in are ignored)."""
    have = {m.participant_id for m in _members(s, group_id)}
    now = utcnow()
    for who in participant_ids:
        if who not in have:
            s.add(ProlificReplicaGroupMember(group_id=group_id, participant_id=who, created_at=now))
    s.flush()


def remove_members(s: Session, group_id: str, participant_ids: list[str]) -> None:
    for member in _members(s, group_id):
        if member.participant_id in participant_ids:
            s.delete(member)
    s.flush()


def create_group(s: Session, body: dict[str, Any]) -> tuple[int, Any]:
    """``POST /participant-groups/`` ``{workspace_id, name, description, participant_ids}``."""
    workspace = _workspace_id(body.get("workspace_id"))
    name = body.get("name")
    if not isinstance(name, str) or not name.strip():
        raise Refusal(400, "name: This field is required.")
    description = body.get("description")
    row = ProlificReplicaParticipantGroup(
        id=new_id(),
        workspace_id=workspace,
        name=name,
        description=description if isinstance(description, str) else None,
        is_deleted=False,
        created_at=utcnow(),
    )
    s.add(row)
    s.flush()
    add_members(s, row.id, _participant_ids(body))
    return 201, group_view(s, row)


def list_groups(s: Session, query: dict[str, str]) -> tuple[int, Any]:
    """``GET /participant-groups/?workspace_id=``: the workspace's groups not deleted."""
    workspace = _workspace_id(query.get("workspace_id"))
    rows = s.scalars(
        select(ProlificReplicaParticipantGroup)
        .where(
            ProlificReplicaParticipantGroup.workspace_id == workspace,
            ProlificReplicaParticipantGroup.is_deleted.is_(False),
        )
        .order_by(ProlificReplicaParticipantGroup.created_at, ProlificReplicaParticipantGroup.id)
    ).all()
    return 200, {"results": [group_view(s, row) for row in rows]}


def membership_view(s: Session, group_id: str) -> dict[str, Any]:
    return {
        "results": [
            {"participant_id": m.participant_id, "datetime_created": m.created_at.isoformat()}
            for m in _members(s, group_id)
        ]
    }


def group_members(s: Session, method: str, group_id: str, body: dict[str, Any]) -> tuple[int, Any]:
    """``GET``, ``POST`` (add) and ``DELETE`` (remove) ``/participant-groups/{id}/participants/``:
    the group's members after the change."""
    _group(s, group_id)
    if method == "POST":
        add_members(s, group_id, _participant_ids(body))
    elif method == "DELETE":
        remove_members(s, group_id, _participant_ids(body))
    return 200, membership_view(s, group_id)


def in_group(s: Session, group_ids: list[str], participant_id: str) -> bool:
    found = s.scalar(
        select(ProlificReplicaGroupMember.group_id).where(
            ProlificReplicaGroupMember.group_id.in_(group_ids),
            ProlificReplicaGroupMember.participant_id == participant_id,
        )
    )
    return found is not None


def barred(s: Session, study: ProlificReplicaStudy, participant_id: str) -> str | None:
    """Why the study keeps the participant out (None: they may take part): a submission of it
    already, a study of ``previous_studies_blocklist`` taken, a group of ``participant_group_blocklist`` joined, or
    no group of ``participant_group_allowlist``."""
    again = s.scalar(
        select(ProlificReplicaSubmission.id).where(
            ProlificReplicaSubmission.study_id == study.id,
            ProlificReplicaSubmission.participant_id == participant_id,
        )
    )
    if again is not None:
        return "they took part in it already (one submission per participant)"
    for item in study.fields.get("filters") or []:
        values = list(item.get("selected_values") or [])
        kind = item.get("filter_id")
        if kind == "previous_studies_blocklist":
            taken = s.scalar(
                select(ProlificReplicaSubmission.id).where(
                    ProlificReplicaSubmission.study_id.in_(values),
                    ProlificReplicaSubmission.participant_id == participant_id,
                )
            )
            if taken is not None:
                return "they took part in a study of its previous_studies_blocklist"
        if kind == "participant_group_blocklist" and in_group(s, values, participant_id):
            return "they are in a participant group of its participant_group_blocklist"
        if kind == "participant_group_allowlist" and not in_group(s, values, participant_id):
            return "they are in no participant group of its participant_group_allowlist"
    return None


def code_actions(s: Session, code: dict[str, Any], participant_id: str) -> None:
    """A completion code's group actions, carried out for the participant who gave it."""
    for action in code.get("actions") or []:
        if not isinstance(action, dict):
            continue
        group = action.get("participant_group")
        if action.get("action") == "ADD_TO_PARTICIPANT_GROUP" and isinstance(group, str):
            if s.get(ProlificReplicaParticipantGroup, group) is not None:
                add_members(s, group, [participant_id])
        if action.get("action") == "REMOVE_FROM_PARTICIPANT_GROUP" and isinstance(group, str):
            remove_members(s, group, [participant_id])


ROUTES: list[tuple[str, re.Pattern[str], str]] = [
    ("POST", re.compile(r"studies/"), "create_study"),
    ("GET", re.compile(r"studies/(?P<id>[0-9a-f]{24})/"), "get_study"),
    ("PATCH", re.compile(r"studies/(?P<id>[0-9a-f]{24})/"), "update_study"),
    ("POST", re.compile(r"studies/(?P<id>[0-9a-f]{24})/transition/"), "transition_study"),
    ("GET", re.compile(r"studies/(?P<id>[0-9a-f]{24})/submissions/counts/"), "submission_counts"),
    ("GET", re.compile(r"submissions/"), "list_submissions"),
    ("POST", re.compile(r"submissions/bulk-approve/"), "bulk_approve"),
    ("POST", re.compile(r"submissions/bonus-payments/"), "set_up_bonuses"),
    ("GET", re.compile(r"submissions/(?P<id>[0-9a-f]{24})/"), "get_submission"),
    ("POST", re.compile(r"submissions/(?P<id>[0-9a-f]{24})/transition/"), "transition_submission"),
    ("POST", re.compile(r"bulk-bonus-payments/(?P<id>[0-9a-f]{24})/pay/"), "pay_bonuses"),
    ("GET", re.compile(r"projects/(?P<id>[0-9a-f]{24})/"), "get_project"),
    ("GET", re.compile(r"workspaces/(?P<id>[0-9a-f]{24})/balance/"), "get_balance"),
    ("GET", re.compile(r"workspaces/"), "list_workspaces"),
    ("POST", re.compile(r"study-cost-calculator/"), "study_cost"),
    ("GET", re.compile(r"reward-recommendations/"), "reward_recommendations"),
    ("POST", re.compile(r"messages/"), "send_message"),
    ("GET", re.compile(r"messages/"), "list_messages"),
    ("POST", re.compile(r"messages/bulk/"), "bulk_message"),
    ("GET", re.compile(r"hooks/event-types/"), "event_types"),
    ("POST", re.compile(r"hooks/secrets/"), "create_secret"),
    ("GET", re.compile(r"hooks/secrets/"), "list_secrets"),
    ("POST", re.compile(r"hooks/subscriptions/"), "create_subscription"),
    ("GET", re.compile(r"hooks/subscriptions/"), "list_subscriptions"),
    ("GET", re.compile(r"hooks/subscriptions/(?P<id>[0-9a-f]{24})/"), "get_subscription"),
    ("POST", re.compile(r"hooks/subscriptions/(?P<id>[0-9a-f]{24})/"), "confirm_subscription"),
    (
        "GET",
        re.compile(r"hooks/subscriptions/(?P<id>[0-9a-f]{24})/events/"),
        "subscription_events",
    ),
    ("POST", re.compile(r"participant-groups/"), "create_group"),
    ("GET", re.compile(r"participant-groups/"), "list_groups"),
    ("GET", re.compile(r"participant-groups/(?P<id>[0-9a-f]{24})/"), "get_group"),
    *(
        (method, re.compile(r"participant-groups/(?P<id>[0-9a-f]{24})/participants/"), "members")
        for method in ("GET", "POST", "DELETE")
    ),
]


def handle(
    db: Database,
    method: str,
    path: str,
    query: dict[str, str],
    raw: bytes,
    workspace: Workspace = Workspace(),
    changes: list[StudyChange] | None = None,
    headers: dict[str, str] | None = None,
) -> tuple[int, Any]:
    """Prolific's answer (status, JSON body) to one request under ``/api/v1/``; a study's change
    of status is added to ``changes`` (for its ``study.status.change`` webhook), the answer's
    own headers (a subscription's ``X-Hook-Secret``) to ``headers``."""
    path = path.lstrip("/")
    known = [(m, name, p.fullmatch(path)) for m, p, name in ROUTES]
    matches = [(m, name, found) for m, name, found in known if found]
    if not matches:
        return 404, error_body(404, f"No endpoint /api/v1/{path}.")
    chosen = [(name, found) for m, name, found in matches if m == method]
    if not chosen:
        return 405, error_body(405, f'Method "{method}" not allowed.')
    name, found = chosen[0]
    body: Any = {}
    if raw:
        try:
            body = json.loads(raw)
        except ValueError:
            return 400, error_body(400, "JSON parse error.")
    if not isinstance(body, dict):
        return 400, error_body(400, "The body must be a JSON object.")
    ident = found.groupdict().get("id", "")
    try:
        with db.write() as s:
            due = publish_due(s)
            if changes is not None:
                changes.extend(due)
            if name == "create_study":
                return create_study(s, body)
            if name == "get_study":
                return 200, study_view(s, _study(s, ident))
            if name in ("update_study", "transition_study"):
                before = _study(s, ident).status
                change = update_study if name == "update_study" else transition_study
                answer = change(s, ident, body)
                study = _study(s, ident)
                if changes is not None and study.status != before:
                    changes.append(StudyChange(study.id, study.status, utcnow()))
                return answer
            if name == "list_submissions":
                return list_submissions(s, query)
            if name == "submission_counts":
                return submission_counts(s, ident)
            if name == "bulk_approve":
                return bulk_approve(s, body)
            if name == "set_up_bonuses":
                return set_up_bonuses(s, body)
            if name == "get_submission":
                return 200, submission_detail(s, _submission(s, ident))
            if name == "transition_submission":
                return transition_submission(s, ident, body)
            if name == "get_project":
                if ident != PROJECT_ID:
                    raise Refusal(404, f"Project {ident} not found.")
                return 200, {"id": PROJECT_ID, "title": "Rehearsals", "workspace": WORKSPACE_ID}
            if name == "get_balance":
                if ident != WORKSPACE_ID:
                    raise Refusal(404, f"Workspace {ident} not found.")
                return 200, balance(s, workspace)
            if name == "study_cost":
                return study_cost(body)
            if name == "reward_recommendations":
                return reward_recommendations(query)
            if name == "send_message":
                return send_message(s, body)
            if name == "bulk_message":
                return bulk_message(s, body)
            if name == "list_messages":
                return list_messages(s, query)
            if name == "list_workspaces":
                return 200, {"results": [{"id": WORKSPACE_ID, "title": "Rehearsals"}]}
            if name == "event_types":
                return 200, {"results": [{"event_type": e} for e in EVENT_TYPES]}
            if name == "create_secret":
                return create_secret(s, body)
            if name == "list_secrets":
                return list_secrets(s, query)
            if name == "create_subscription":
                return create_subscription(s, body, headers)
            if name == "list_subscriptions":
                return list_subscriptions(s, query)
            if name == "get_subscription":
                return 200, subscription_view(_subscription(s, ident))
            if name == "confirm_subscription":
                return confirm_subscription(s, ident, body)
            if name == "subscription_events":
                return subscription_events(s, ident, query)
            if name == "create_group":
                return create_group(s, body)
            if name == "list_groups":
                return list_groups(s, query)
            if name == "get_group":
                return 200, group_view(s, _group(s, ident))
            if name == "members":
                return group_members(s, method, ident, body)
            return pay_bonuses(s, ident)
    except Refusal as refused:
        return refused.status, error_body(refused.status, refused.detail)


class ReplicaTransport(httpx.BaseTransport):
    """The client's requests answered by the replica inside this process (no network): the
    same code runs as against Prolific, with the token checked as Prolific does."""

    def __init__(
        self,
        db: Database,
        token: str,
        prefix: str = "/prolific/api/v1/",
        workspace: Workspace = Workspace(),
    ) -> None:
        self.db = db
        self.token = token
        self.prefix = prefix
        self.workspace = workspace

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        headers: dict[str, str] = {}
        if request.headers.get("Authorization") != f"Token {self.token}":
            status, body = 401, error_body(401, "Invalid token.")
        else:
            path = request.url.path
            path = path[len(self.prefix) :] if path.startswith(self.prefix) else path
            query = {k: v[-1] for k, v in parse_qs(request.url.query.decode()).items()}
            status, body = handle(
                self.db, request.method, path, query, request.read(), self.workspace, None, headers
            )
        content = b"" if body is None else json.dumps(body).encode()
        return httpx.Response(
            status, content=content, headers={"Content-Type": "application/json", **headers}
        )


def submission_payload(submission: dict[str, Any]) -> dict[str, Any]:
    """The body of the replica's ``submission.status.change`` for a submission."""
    return {
        "event_type": "submission.status.change",
        "resource_id": submission["id"],
        "study_id": submission["study_id"],
        "participant_id": submission["participant_id"],
        "status": submission["status"],
    }


def study_payload(change: StudyChange) -> dict[str, Any]:
    """Prolific's ``study.status.change`` body: the study's id as ``resource_id``, its new
    status, ``metadata``."""
    return {
        "resource_id": change.study_id,
        "event_type": "study.status.change",
        "metadata": {},
        "status": change.status,
    }


def status_event(
    secret: str, submission: dict[str, Any], timestamp: int
) -> tuple[dict[str, str], bytes]:
    """The replica's ``submission.status.change`` webhook for a submission, signed as Prolific
    signs it: the headers and the body."""
    body = json.dumps(submission_payload(submission)).encode()
    # When the status changed: the replica sends at once.
    return signed(secret, body, timestamp, str(timestamp)), body


def study_status_event(
    secret: str, change: StudyChange, timestamp: int
) -> tuple[dict[str, str], bytes]:
    """The replica's ``study.status.change`` webhook, signed as its submission events are; its
    ``X-Timestamp`` is the change's own time, to the microsecond, so that two changes in one
    second keep their order."""
    body = json.dumps(study_payload(change)).encode()
    return signed(secret, body, timestamp, change.at.isoformat()), body


def signed(secret: str, body: bytes, timestamp: int, event_time: str) -> dict[str, str]:
    """A webhook's headers, as Prolific signs its deliveries: the signature of the timestamp
    and the body, a new event id, and ``X-Timestamp`` (``event_time``: when it happened)."""
    stamp = str(timestamp)
    return {
        "Content-Type": "application/json",
        "X-Prolific-Request-Signature": signature(secret, stamp, body),
        "X-Prolific-Request-Timestamp": stamp,
        "X-Event-ID": secrets.token_hex(16),
        "X-Timestamp": event_time,
    }
