"""Studies: made as drafts and refused for the fields Prolific refuses, changed, published,
scheduled, paused and started with transitions."""

from __future__ import annotations

import re
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from server.app.platforms.prolific_replica.base import (
    PROJECT_ID,
    Refusal,
    StudyChange,
    _positive_int,
    _study,
    new_id,
)
from server.app.platforms.prolific_replica.views import places_taken, study_view
from server.app.storage.models import utcnow
from server.app.storage.replica_models import (
    ProlificReplicaParticipantGroup,
    ProlificReplicaStudy,
)
from server.app.study_file import prolific_least_maximum_minutes

STUDY_ACTIONS = {
    "PUBLISH": ({"UNPUBLISHED"}, "ACTIVE"),
    "SCHEDULE_PUBLISH": ({"UNPUBLISHED"}, "SCHEDULED"),
    "CANCEL_PUBLISH": ({"SCHEDULED"}, "UNPUBLISHED"),
    "PAUSE": ({"ACTIVE"}, "PAUSED"),
    "START": ({"PAUSED", "AWAITING REVIEW"}, "ACTIVE"),
    "STOP": ({"ACTIVE", "PAUSED", "AWAITING REVIEW"}, "COMPLETED"),
}
LARGEST_MAXIMUM_MINUTES = 24 * 60 - 1
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
