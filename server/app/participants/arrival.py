"""Arrival from each platform (lab, Prolific, MTurk): who may start, who comes back, and the
participant row and token made for a newcomer.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import ColumnElement, Connection, func, select
from sqlalchemy.exc import IntegrityError

from server.app.config import StudyConfig
from server.app.errors import ApiError, TurnedAway
from server.app.participants.tokens import (
    ADD_TOKEN,
    IN_PROGRESS,
    PARTICIPANTS,
    PREVIEW_ASSIGNMENT,
    advisory_lock_key,
    new_token,
    participant_by_token,
    reactivate,
    restore_status,
    set_status,
)
from server.app.platforms.prolific_replica import REPLICA_PATH, is_replica_study
from server.app.schemas import (
    ArrivalRequest,
)
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import (
    utcnow,
)
from server.app.storage.records import Record, add, load, load_all


@dataclass(frozen=True)
class Platform:
    name: str  # mturk, prolific or lab
    worker_id: str | None = None
    assignment_id: str | None = None
    hit_id: str | None = None
    submit_to: str | None = None


def classify_arrival(
    request: ArrivalRequest, study: StudyConfig, settings: Settings, own_origin: str | None
) -> Platform | None:
    """The arrival's platform and ids; None for an MTurk preview. Bad parameters get 400,
    arrivals the study does not accept are turned away."""
    if request.assignment_id == PREVIEW_ASSIGNMENT:
        return None
    mturk = [request.assignment_id, request.hit_id, request.worker_id, request.turk_submit_to]
    prolific = [request.prolific_pid, request.study_id, request.session_id]
    if any(v is not None for v in mturk) and any(v is not None for v in prolific):
        raise ApiError(400, "the link has both Mechanical Turk and Prolific parameters")
    if any(v is not None for v in mturk):
        missing = [
            name
            for name, value in zip(
                ("assignmentId", "hitId", "workerId", "turkSubmitTo"), mturk, strict=True
            )
            if value is None
        ]
        if missing:
            raise ApiError(400, f"the Mechanical Turk link lacks {', '.join(missing)}")
        submit_to = _check_submit_to(str(request.turk_submit_to), settings, own_origin)
        platform = Platform(
            "mturk", request.worker_id, request.assignment_id, request.hit_id, submit_to
        )
    elif any(v is not None for v in prolific):
        missing = [
            name
            for name, value in zip(
                ("PROLIFIC_PID", "STUDY_ID", "SESSION_ID"), prolific, strict=True
            )
            if value is None
        ]
        if missing:
            raise ApiError(400, f"the Prolific link lacks {', '.join(missing)}")
        platform = Platform("prolific", request.prolific_pid, request.session_id, request.study_id)
    else:
        platform = Platform("lab")
    mode = study.completion.mode
    if platform.name == "lab":
        if mode != "lab" and not study.allow_anonymous:
            where = "Mechanical Turk" if mode == "mturk" else "Prolific"
            raise TurnedAway(
                "Please open the study from its link",
                f"This study runs on {where}: please open it from the study's page there.",
            )
    elif platform.name != mode:
        raise TurnedAway(
            "This link is for another platform",
            f"This study does not run on {'Mechanical Turk' if platform.name == 'mturk' else 'Prolific'}.",
        )
    return platform


def _check_submit_to(value: str, settings: Settings, own_origin: str | None) -> str:
    """The origin the completion form posts to: exactly one of MTurk's (or this server's, for
    the local replica), written as the accepted origin, never as the raw parameter. Matching
    whole origins leaves nothing for browsers and URL parsers to read differently (a
    backslash, user info, a port, a control character, a bracketed host)."""
    allowed = {origin.lower(): origin for origin in settings.submit_origins}
    if own_origin is not None and own_origin.isascii() and own_origin.isprintable():
        allowed[own_origin.lower()] = own_origin
    candidate = value[:-1] if value.endswith("/") else value
    origin = allowed.get(candidate.lower())
    if origin is None:
        raise ApiError(
            400,
            f"turkSubmitTo must be one of {', '.join(sorted(settings.submit_origins))} "
            f"(or this server, for its Mechanical Turk replica), got {value[:100]!a}",
        )
    return origin


@dataclass
class Arrival:
    participant: Record
    token: str | None  # a new token, or None when the participant's cookie is still valid
    resumed: bool


Room = Callable[[Connection, datetime], bool]  # may a new participant go in now?


def arrive(
    db: Database,
    platform: Platform,
    cookie_token: str | None,
    study: StudyConfig,
    room: Room | None = None,
) -> Arrival:
    """Create the participant, or find the one this arrival resumes: MTurk and Prolific
    participants by their (worker, assignment) ids, lab participants by their cookie. A new
    participant for whom ``room`` finds no place waits for one (``places``)."""
    try:
        return _arrive(db, platform, cookie_token, study, room)
    except IntegrityError:
        # The same worker and assignment arrived twice at once (PostgreSQL): the other
        # arrival created the participant, this one resumes it.
        return _arrive(db, platform, cookie_token, study, room)


def _arrive(
    db: Database,
    platform: Platform,
    cookie_token: str | None,
    study: StudyConfig,
    room: Room | None,
) -> Arrival:
    now = utcnow()
    with db.transaction() as c:
        current = None
        if cookie_token and len(cookie_token) <= 128:
            current = participant_by_token(c, cookie_token)
        if platform.name == "lab":
            if current is not None and current.platform == "lab":
                reactivate(c, current, now)
                current.save(c)
                return Arrival(current, None, True)
            return Arrival(*_create(c, platform, now, room), False)
        worker = (platform.worker_id or "").lower()
        if c.dialect.name == "postgresql" and not study.allow_repeat_workers:
            # One worker's arrivals one at a time, until this one commits (SQLite's writes are
            # one at a time already: BEGIN IMMEDIATE).
            key = advisory_lock_key(f"bam-study worker {platform.name} {worker}")
            c.execute(select(func.pg_advisory_xact_lock(key)))
        if c.dialect.name == "postgresql" and platform.name == "mturk":
            # And one assignment's (who holds it is decided below), always after the worker's.
            key = advisory_lock_key(f"bam-study assignment {platform.assignment_id}")
            c.execute(select(func.pg_advisory_xact_lock(key)))
        # (Ids that differ in case only, stored before they were compared so, are one worker:
        # the participation with the id as given comes first, then the oldest.)
        candidates = load_all(
            c,
            PARTICIPANTS,
            PARTICIPANTS.c.platform == platform.name,
            same_worker(worker),
            PARTICIPANTS.c.assignment_id == platform.assignment_id,
            order_by=PARTICIPANTS.c.id,
        )
        existing = min(candidates, key=lambda p: p.worker_id != platform.worker_id, default=None)
        coming_back = existing is None or existing.status == "returned"
        if (
            coming_back
            and not study.allow_repeat_workers
            and _took_part(c, platform, None if existing is None else existing.id)
        ):
            raise TurnedAway(
                "You have already taken part",
                "Our records show that you have already taken part in this study, which allows "
                "each person only once. Please return this task; thank you for your interest.",
            )
        if platform.name == "mturk":
            # MTurk gives a returned assignment to the next worker who accepts it, who holds it
            # from then on: the worker who returned it cannot take it back.
            others = load_all(
                c,
                PARTICIPANTS,
                PARTICIPANTS.c.platform == "mturk",
                PARTICIPANTS.c.assignment_id == platform.assignment_id,
                ~same_worker(worker),
                PARTICIPANTS.c.status.not_in(("returned", "declined")),
            )
            if existing is not None and existing.status == "returned" and others:
                raise TurnedAway(
                    "You returned this task",
                    "You returned this task, and its assignment went to another worker, who "
                    "holds it now. To take part, accept the task again on Mechanical Turk: you "
                    "will get an assignment of your own.",
                    409,
                )
            in_progress = [p for p in others if p.status in (*IN_PROGRESS, "abandoned")]
            mark_returned(c, in_progress, now, "assignment taken by another worker")
        if existing is None:
            return Arrival(*_create(c, platform, now, room), False)
        if platform.name == "prolific" and existing.status == "returned":
            # Released on Prolific's word (RETURNED or TIMED-OUT): the place went to another.
            raise TurnedAway(
                "This study has ended for you",
                "Prolific shows that this study was returned or that its time ran out, so your "
                "place has gone to another participant and it cannot be continued. What you did "
                "is kept. Thank you for your interest.",
            )
        if existing.status in ("abandoned", "returned"):
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


def _took_part(c: Connection, platform: Platform, other_than: int | None) -> bool:
    """The worker has another participation that still counts: any but one returned (the
    assignment went to another worker) or declined (no consent), whatever its status. The
    worker's arrivals are serialised (``_arrive``), so two arriving at once cannot both find
    none."""
    query = (
        select(func.count())
        .select_from(PARTICIPANTS)
        .where(
            PARTICIPANTS.c.platform == platform.name,
            same_worker(platform.worker_id or ""),
            PARTICIPANTS.c.status.not_in(("returned", "declined")),
        )
    )
    if other_than is not None:
        query = query.where(PARTICIPANTS.c.id != other_than)
    return bool(c.scalar(query))


def same_worker(worker_id: str) -> ColumnElement[bool]:
    """The participant is this worker's, whatever the case of the id: an id typed or pasted in
    another case is the same worker (ids are stored as they came, so no stored row changes)."""
    return func.lower(PARTICIPANTS.c.worker_id) == worker_id.lower()


def mark_returned(c: Connection, participants: list[Record], now: datetime, note: str) -> None:
    for participant in participants:
        set_status(c, participant, "returned", now, note=note)
        participant.save(c)


def return_assignment(c: Connection, worker_id: str, assignment_id: str) -> None:
    """The worker returned the HIT (the local MTurk replica says so at once; MTurk itself does
    not): their participation with that assignment, if it is going on, is returned."""
    going_on = load_all(
        c,
        PARTICIPANTS,
        PARTICIPANTS.c.platform == "mturk",
        same_worker(worker_id),
        PARTICIPANTS.c.assignment_id == assignment_id,
        PARTICIPANTS.c.status.in_((*IN_PROGRESS, "abandoned")),
    )
    mark_returned(c, going_on, utcnow(), "returned the HIT")


def _create(
    c: Connection, platform: Platform, now: datetime, room: Room | None
) -> tuple[Record, str]:
    status = "arrived" if room is None or room(c, now) else "waiting"
    submit_to = platform.submit_to
    if platform.name == "prolific" and platform.hit_id is not None:
        # A study of this server's Prolific replica: the participant goes back to it.
        submit_to = REPLICA_PATH if is_replica_study(c, platform.hit_id) else None
    token, token_hash = new_token()
    participant_id = add(
        c,
        PARTICIPANTS,
        token_hash=token_hash,
        platform=platform.name,
        worker_id=platform.worker_id,
        assignment_id=platform.assignment_id,
        hit_id=platform.hit_id,
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


# -- requests that change something -----------------------------------------------------------
