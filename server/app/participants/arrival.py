"""Arrival from each platform (``server.app.platform_registry``: the lab, Prolific, MTurk): who
may start, who comes back, and the participant row and token made for a newcomer.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import ColumnElement, Connection, func, select
from sqlalchemy.exc import IntegrityError

from server.app import platform_registry as registry
from server.app.errors import ApiError, TurnedAway
from server.app.participants.statuses import reactivate, restore_status, set_status
from server.app.participants.tokens import ADD_TOKEN, new_token, participant_by_token
from server.app.platforms.base import ArrivalIds
from server.app.schemas import (
    ArrivalRequest,
)
from server.app.settings import Settings
from server.app.storage.db import Database, advisory_lock_key
from server.app.storage.models import utcnow
from server.app.storage.records import Record, add, load, load_all
from server.app.storage.tables import ERASURES, PARTICIPANTS
from server.app.storage.vocabulary import IN_PROGRESS, ParticipantStatus
from server.app.study_file import StudyConfig

# A worker's participations that no longer count: the task returned, consent declined, or the
# device turned away by the device check (the worker may come back on another device).
NOT_COUNTED = (
    ParticipantStatus.RETURNED,
    ParticipantStatus.DECLINED,
    ParticipantStatus.INCOMPATIBLE,
)
# Participations going on (an abandoned participant may come back).
GOING_ON = (*IN_PROGRESS, ParticipantStatus.ABANDONED)


def classify_arrival(
    request: ArrivalRequest, study: StudyConfig, settings: Settings, own_origin: str | None
) -> ArrivalIds | None:
    """The arrival's platform and ids (the platform whose link parameters it has; none: the
    lab); None for a preview. Bad parameters get 400, arrivals the study does not accept are
    turned away."""
    params = request.params()
    given = [p for p in registry.platforms() if any(name in params for name in p.parameters)]
    if len(given) > 1:
        raise ApiError(
            400, f"the link has both {' and '.join(p.display_name for p in given)} parameters"
        )
    platform = given[0] if given else registry.platform("lab")
    ids = platform.arrival(params, settings, own_origin)
    if ids is None:
        return None
    mode = study.completion.mode
    if ids.name == "lab":
        if mode != "lab" and not study.allow_anonymous:
            raise TurnedAway(
                "Please open the study from its link",
                f"This study runs on {registry.platform(mode).display_name}: please open it "
                "from the study's page there.",
            )
    elif ids.name != mode:
        raise TurnedAway(
            "This link is for another platform",
            f"This study does not run on {platform.display_name}.",
        )
    return ids


@dataclass
class Arrival:
    participant: Record
    token: str | None  # a new token, or None when the participant's cookie is still valid
    resumed: bool


Room = Callable[[Connection, datetime], bool]  # may a new participant go in now?


def arrive(
    db: Database,
    ids: ArrivalIds,
    cookie_token: str | None,
    study: StudyConfig,
    room: Room | None = None,
) -> Arrival:
    """Create the participant, or find the one this arrival resumes: MTurk and Prolific
    participants by their (worker, assignment) ids, lab participants by their cookie. A new
    participant for whom ``room`` finds no place waits for one (``places``)."""
    try:
        return _arrive(db, ids, cookie_token, study, room)
    except IntegrityError:
        # The same worker and assignment arrived twice at once (PostgreSQL): the other
        # arrival created the participant, this one resumes it.
        return _arrive(db, ids, cookie_token, study, room)


def _arrive(
    db: Database,
    ids: ArrivalIds,
    cookie_token: str | None,
    study: StudyConfig,
    room: Room | None,
) -> Arrival:
    now = utcnow()
    with db.transaction() as c:
        current = None
        if cookie_token and len(cookie_token) <= 128:
            current = participant_by_token(c, cookie_token)
        platform = registry.platform(ids.name)
        # No platform ids (the lab): the cookie says who it is.
        if ids.platform_participant_id is None:
            if current is not None and current.platform == ids.name:
                reactivate(c, current, now)
                current.save(c)
                return Arrival(current, None, True)
            return Arrival(*_create(c, ids, now, room), False)
        worker = (ids.platform_participant_id or "").lower()
        if c.dialect.name == "postgresql" and not study.allow_repeat_workers:
            # One worker's arrivals one at a time, until this one commits (SQLite's writes are
            # one at a time already: BEGIN IMMEDIATE).
            key = advisory_lock_key(f"bam-study worker {ids.name} {worker}")
            c.execute(select(func.pg_advisory_xact_lock(key)))
        if c.dialect.name == "postgresql" and platform.exclusive_assignments:
            # And one assignment's (who holds it is decided below), always after the worker's.
            key = advisory_lock_key(f"bam-study assignment {ids.platform_submission_id}")
            c.execute(select(func.pg_advisory_xact_lock(key)))
        # (Ids that differ in case only, stored before they were compared so, are one worker:
        # the participation with the id as given comes first, then the oldest.)
        candidates = load_all(
            c,
            PARTICIPANTS,
            PARTICIPANTS.c.platform == ids.name,
            same_worker(worker),
            PARTICIPANTS.c.platform_submission_id == ids.platform_submission_id,
            order_by=PARTICIPANTS.c.id,
        )
        existing = min(
            candidates,
            key=lambda p: p.platform_participant_id != ids.platform_participant_id,
            default=None,
        )
        coming_back = existing is None or existing.status == ParticipantStatus.RETURNED
        if (
            coming_back
            and not study.allow_repeat_workers
            and _took_part(c, ids, None if existing is None else existing.id)
        ):
            raise TurnedAway(
                "You have already taken part",
                "Our records show that you have already taken part in this study, which allows "
                "each person only once. Please return this task; thank you for your interest.",
            )
        if platform.exclusive_assignments:
            # MTurk gives a returned assignment to the next worker who accepts it, who holds it
            # from then on: the worker who returned it cannot take it back.
            others = load_all(
                c,
                PARTICIPANTS,
                PARTICIPANTS.c.platform == ids.name,
                PARTICIPANTS.c.platform_submission_id == ids.platform_submission_id,
                ~same_worker(worker),
                PARTICIPANTS.c.status.not_in(NOT_COUNTED),
            )
            if existing is not None and existing.status == ParticipantStatus.RETURNED and others:
                raise TurnedAway(
                    "You returned this task",
                    "You returned this task, and its assignment went to another worker, who "
                    "holds it now. To take part, accept the task again on "
                    f"{platform.display_name}: you will get an assignment of your own.",
                    409,
                )
            in_progress = [p for p in others if p.status in GOING_ON]
            mark_returned(c, in_progress, now, "assignment taken by another worker")
        if existing is None:
            return Arrival(*_create(c, ids, now, room), False)
        if platform.released is not None and existing.status == ParticipantStatus.RETURNED:
            # Released on the platform's word: the place went to another.
            raise TurnedAway(platform.released.title, platform.released.message)
        if existing.status in (ParticipantStatus.ABANDONED, ParticipantStatus.RETURNED):
            restore_status(c, existing, now)
        token = None
        if current is None or current.id != existing.id:
            # Another browser (or the cookie is blocked in the platform's iframe): the
            # platform's ids identify the participant, and this browser gets a token of its own
            # beside the others' (the sequence numbers keep their requests in order).
            token, token_hash = new_token()
            c.execute(
                ADD_TOKEN,
                {"token_hash": token_hash, "participant_id": existing.id, "created_at": now},
            )
        existing.save(c)
        return Arrival(existing, token, True)


def _took_part(c: Connection, ids: ArrivalIds, other_than: int | None) -> bool:
    """The worker has another participation that still counts: any but one returned (the
    assignment went to another worker) or declined (no consent), whatever its status. The
    worker's arrivals are serialised (``_arrive``), so two arriving at once cannot both find
    none."""
    query = (
        select(func.count())
        .select_from(PARTICIPANTS)
        .where(
            PARTICIPANTS.c.platform == ids.name,
            same_worker(ids.platform_participant_id or ""),
            PARTICIPANTS.c.status.not_in(NOT_COUNTED),
        )
    )
    if other_than is not None:
        query = query.where(PARTICIPANTS.c.id != other_than)
    return bool(c.scalar(query))


def same_worker(platform_participant_id: str) -> ColumnElement[bool]:
    """The participant is this worker's, whatever the case of the id: an id typed or pasted in
    another case is the same worker (ids are stored as they came, so no stored row changes)."""
    return func.lower(PARTICIPANTS.c.platform_participant_id) == platform_participant_id.lower()


def mark_returned(c: Connection, participants: list[Record], now: datetime, note: str) -> None:
    for participant in participants:
        set_status(c, participant, ParticipantStatus.RETURNED, now, note=note)
        participant.save(c)


def return_assignment(
    c: Connection, platform_participant_id: str, platform_submission_id: str
) -> None:
    """The worker returned the HIT (the local MTurk replica says so at once; MTurk itself does
    not): their participation with that assignment, if it is going on, is returned."""
    going_on = load_all(
        c,
        PARTICIPANTS,
        PARTICIPANTS.c.platform == "mturk",
        same_worker(platform_participant_id),
        PARTICIPANTS.c.platform_submission_id == platform_submission_id,
        PARTICIPANTS.c.status.in_(GOING_ON),
    )
    mark_returned(c, going_on, utcnow(), "returned the HIT")


def _create(c: Connection, ids: ArrivalIds, now: datetime, room: Room | None) -> tuple[Record, str]:
    status = (
        ParticipantStatus.ARRIVED if room is None or room(c, now) else ParticipantStatus.WAITING
    )
    submit_to = registry.platform(ids.name).submit_to(c, ids)
    token, token_hash = new_token()
    participant_id = add(
        c,
        PARTICIPANTS,
        **_next_number(c),
        token_hash=token_hash,
        platform=ids.name,
        platform_participant_id=ids.platform_participant_id,
        platform_submission_id=ids.platform_submission_id,
        platform_study_id=ids.platform_study_id,
        submit_to=submit_to,
        status=status,
        next_seq=1,
        created_at=now,
        last_seen_at=now,
    )
    participant = load(c, PARTICIPANTS, PARTICIPANTS.c.id == participant_id)
    assert participant is not None
    set_status(c, participant, status, now)
    participant.save(c)
    return participant, token


def _next_number(c: Connection) -> dict[str, int]:
    """SQLite gives a new row the largest id there plus one, so erasing the newest participant
    would give their number to the next arrival (two people under one number in
    ``erasures.csv``): past the erased numbers too. (One writer at a time on SQLite; PostgreSQL's
    sequence never gives a number twice.)"""
    if c.dialect.name != "sqlite":
        return {}
    highest = c.execute(
        select(
            select(func.max(PARTICIPANTS.c.id)).scalar_subquery(),
            select(func.max(ERASURES.c.participant_id)).scalar_subquery(),
        )
    ).one()
    return {"id": max(number or 0 for number in highest) + 1}


# -- requests that change something -----------------------------------------------------------
