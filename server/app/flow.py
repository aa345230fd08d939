"""The participant flow: arrival, consent, domain assignment, the order of learning sessions,
statuses, completion; and ``perform``, through which every request that changes something goes.

``perform`` runs a request in one write transaction: it checks the participant's token and the
request's sequence number, lets the handler change the state, and stores the event with the
response it answers, so that a retried request is answered identically and stored once.

The request path works on ``records.Record`` rows with SQLAlchemy Core (see ``records.py``).
"""

from __future__ import annotations

import hashlib
import json
import random
import secrets
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from functools import cache
from typing import Any

import numpy as np
from sqlalchemy import Connection, and_, bindparam, func, insert, or_, select
from sqlalchemy.exc import IntegrityError

from server.app.config import LikertQuestion, Question, StudyConfig, TextQuestion
from server.app.db import Database
from server.app.errors import ApiError, InvalidInput, TurnedAway
from server.app.models import (
    Event,
    LearnerUpdate,
    LearningSession,
    Participant,
    ParticipantToken,
    QuestionnaireAnswer,
    StatusChange,
    utcnow,
)
from server.app.records import Record, add, load, load_all, table_of
from server.app.schemas import (
    ArrivalRequest,
    Completion,
    ParticipantBrief,
    ParticipantState,
    Progress,
    SeqRequest,
    SessionSummary,
)
from server.app.settings import Settings
from server.app.state import ServerState
from server.domains import make as make_environment

PREVIEW_ASSIGNMENT = "ASSIGNMENT_ID_NOT_AVAILABLE"
# Flow statuses, in order; "returned" (MTurk: the HIT was returned), "abandoned" (idle too long)
# and "declined" (no consent) end the flow; exclusion is a separate mark.
# "questionnaire": the post-study questionnaire is being answered (a study file with one).
FLOW_STATUSES = (
    "arrived",
    "consented",
    "tutorial",
    "teaching",
    "questionnaire",
    "completed",
    "submitted",
)
IN_PROGRESS = ("arrived", "consented", "tutorial", "teaching", "questionnaire")
# "waiting": arrived while the study was full, for a place (``places``); not yet in the flow.
STATUSES = ("waiting", *FLOW_STATUSES, "declined", "returned", "abandoned")
CODE_ALPHABET = "ABCDEFGHJKLMNPQRSTUVWXYZ23456789"
TOKEN_HEADER = "X-Participant-Token"

PARTICIPANTS = table_of(Participant)
SESSIONS = table_of(LearningSession)
EVENTS = table_of(Event)
UPDATES = table_of(LearnerUpdate)
STATUS_CHANGES = table_of(StatusChange)
TOKENS = table_of(ParticipantToken)
ANSWERS = table_of(QuestionnaireAnswer)

_random = secrets.SystemRandom()
# Prepared: every request looks its participant up by token.
_BY_TOKEN = select(PARTICIPANTS).where(PARTICIPANTS.c.token_hash == bindparam("token_hash"))
_BY_TOKEN_LOCKED = _BY_TOKEN.with_for_update()
# A further browser's token (see ParticipantToken), looked up when the first's does not match.
_BY_FURTHER_TOKEN = select(PARTICIPANTS).where(
    PARTICIPANTS.c.id
    == select(TOKENS.c.participant_id)
    .where(TOKENS.c.token_hash == bindparam("token_hash"))
    .scalar_subquery()
)
_BY_FURTHER_TOKEN_LOCKED = _BY_FURTHER_TOKEN.with_for_update()
_ADD_TOKEN = insert(TOKENS)


def advisory_lock_key(name: str) -> int:
    """A PostgreSQL advisory lock key: the first 8 bytes of sha256(name)."""
    return int.from_bytes(hashlib.sha256(name.encode()).digest()[:8], "big", signed=True)


DOMAIN_LOCK_KEY = advisory_lock_key("bam-study domain assignment")
_LOCK_DOMAIN_ASSIGNMENT = select(func.pg_advisory_xact_lock(DOMAIN_LOCK_KEY))
_STORED_EVENT = select(EVENTS.c.request_hash, EVENTS.c.response).where(
    EVENTS.c.participant_id == bindparam("participant_id"), EVENTS.c.seq == bindparam("seq")
)


# -- identity -------------------------------------------------------------------------------
def new_token() -> tuple[str, str]:
    token = secrets.token_urlsafe(32)
    return token, hash_token(token)


def hash_token(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def participant_by_token(c: Connection, token: str, lock: bool = False) -> Record | None:
    """The participant whose token (any of its browsers') this is; ``lock`` holds its row until
    the transaction ends (PostgreSQL; SQLite writes are serialised already)."""
    token_hash = {"token_hash": hash_token(token)}
    row = c.execute(_BY_TOKEN_LOCKED if lock else _BY_TOKEN, token_hash).mappings().first()
    if row is None:
        further = _BY_FURTHER_TOKEN_LOCKED if lock else _BY_FURTHER_TOKEN
        row = c.execute(further, token_hash).mappings().first()
    return None if row is None else Record(PARTICIPANTS, row)


def participant_for(c: Connection, token: str | None, lock: bool = False) -> Record:
    """The participant whose token this is (401 otherwise); ``lock`` as above."""
    if not token or len(token) > 128:
        raise ApiError(401, "no participant: open the study from its link again")
    participant = participant_by_token(c, token, lock)
    if participant is None:
        raise ApiError(401, "unknown participant token: open the study from its link again")
    return participant


# -- statuses -------------------------------------------------------------------------------
def set_status(
    c: Connection, participant: Record, status: str, now: datetime, note: str | None = None
) -> None:
    participant.status = status
    add(c, STATUS_CHANGES, participant_id=participant.id, status=status, at=now, note=note)


def restore_status(c: Connection, participant: Record, now: datetime) -> None:
    """Back to the flow status the participant had before being marked abandoned or returned."""
    previous = c.scalar(
        select(STATUS_CHANGES.c.status)
        .where(
            STATUS_CHANGES.c.participant_id == participant.id,
            STATUS_CHANGES.c.status.in_(FLOW_STATUSES),
        )
        .order_by(STATUS_CHANGES.c.id.desc())
        .limit(1)
    )
    set_status(c, participant, previous or "arrived", now, note="came back")


def reactivate(c: Connection, participant: Record, now: datetime) -> None:
    """A participant marked abandoned who is active again continues where they were. (One whose
    MTurk assignment went to another worker continues only by arriving with it again.)"""
    if participant.status == "abandoned":
        restore_status(c, participant, now)


def mark_abandoned(db: Database, settings: Settings) -> int:
    """Mark participants idle for longer than ``abandon_minutes`` as abandoned."""
    now = utcnow()
    cutoff = now - timedelta(minutes=settings.abandon_minutes)
    with db.transaction() as c:
        idle = load_all(
            c,
            PARTICIPANTS,
            PARTICIPANTS.c.status.in_(IN_PROGRESS),
            PARTICIPANTS.c.last_seen_at < cutoff,
        )
        for participant in idle:
            since = f"idle since {participant.last_seen_at:%Y-%m-%d %H:%M} UTC"
            set_status(c, participant, "abandoned", now, note=since)
            participant.save(c)
        return len(idle)


# -- arrival --------------------------------------------------------------------------------
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
        if c.dialect.name == "postgresql" and not study.allow_repeat_workers:
            # One worker's arrivals one at a time, until this one commits (SQLite's writes are
            # one at a time already: BEGIN IMMEDIATE).
            key = advisory_lock_key(f"bam-study worker {platform.name} {platform.worker_id}")
            c.execute(select(func.pg_advisory_xact_lock(key)))
        existing = load(
            c,
            PARTICIPANTS,
            PARTICIPANTS.c.platform == platform.name,
            PARTICIPANTS.c.worker_id == platform.worker_id,
            PARTICIPANTS.c.assignment_id == platform.assignment_id,
        )
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
            # MTurk gives a returned assignment to the next worker who accepts it.
            for previous in load_all(
                c,
                PARTICIPANTS,
                PARTICIPANTS.c.platform == "mturk",
                PARTICIPANTS.c.assignment_id == platform.assignment_id,
                PARTICIPANTS.c.worker_id != platform.worker_id,
                PARTICIPANTS.c.status.in_((*IN_PROGRESS, "abandoned")),
            ):
                set_status(c, previous, "returned", now, note="assignment taken by another worker")
                previous.save(c)
        if existing is None:
            return Arrival(*_create(c, platform, now, room), False)
        if existing.status in ("abandoned", "returned"):
            restore_status(c, existing, now)
        token = None
        if current is None or current.id != existing.id:
            # Another browser (or the cookie is blocked in the platform's iframe): the
            # platform's ids identify the participant, and this browser gets a token of its own
            # beside the others' (the sequence numbers keep their requests in order).
            token, token_hash = new_token()
            c.execute(
                _ADD_TOKEN,
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
            PARTICIPANTS.c.worker_id == platform.worker_id,
            PARTICIPANTS.c.status.not_in(("returned", "declined")),
        )
    )
    if other_than is not None:
        query = query.where(PARTICIPANTS.c.id != other_than)
    return bool(c.scalar(query))


def _create(
    c: Connection, platform: Platform, now: datetime, room: Room | None
) -> tuple[Record, str]:
    status = "arrived" if room is None or room(c, now) else "waiting"
    token, token_hash = new_token()
    participant_id = add(
        c,
        PARTICIPANTS,
        token_hash=token_hash,
        platform=platform.name,
        worker_id=platform.worker_id,
        assignment_id=platform.assignment_id,
        hit_id=platform.hit_id,
        submit_to=platform.submit_to,
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
class LazyGenerator:
    """A NumPy generator made on first use: most requests draw nothing (the dynamics of every
    environment here are deterministic), and making one costs more than the rest of a move."""

    def __init__(self, seed: list[int]) -> None:
        self._seed = seed
        self._generator: np.random.Generator | None = None

    def __getattr__(self, name: str) -> Any:
        if self._generator is None:
            self._generator = np.random.default_rng(self._seed)
        return getattr(self._generator, name)


@dataclass
class QueuedUpdate:
    session_id: int
    update_index: int
    episodes: int
    actions: int


@dataclass
class Action:
    """One request being performed (see ``perform``)."""

    c: Connection
    participant: Record
    event: dict[str, Any]  # the event's columns, inserted after the handler
    server: ServerState
    now: datetime
    updates: list[QueuedUpdate] = field(default_factory=list)  # learner updates to queue
    records: list[Record] = field(default_factory=list)  # rows to write back

    def track(self, record: Record) -> Record:
        """Write this row's changes back when the request is done."""
        self.records.append(record)
        return record

    def flush(self) -> None:
        """Write the changes so far (before a query that must see them)."""
        self.participant.save(self.c)
        for record in self.records:
            record.save(self.c)

    @property
    def study(self) -> StudyConfig:
        return self.server.study

    @property
    def settings(self) -> Settings:
        return self.server.settings

    @property
    def seq(self) -> int:
        return int(self.event["seq"])

    def rng(self, seed: int) -> Any:
        """Randomness of this request, reproducible from the session's seed and the seq."""
        return LazyGenerator([seed, self.seq])

    def queue_update(self, session: Record) -> int:
        """Queue the session's next learner update (index ``updates_requested``), which will
        include this request's event."""
        self.updates.append(
            QueuedUpdate(session.id, session.updates_requested, session.episodes, session.actions)
        )
        return int(session.updates_requested)


def request_fingerprint(kind: str, session_id: int | None, body: SeqRequest) -> str:
    text = json.dumps(
        {"kind": kind, "session": session_id, "body": body.model_dump(mode="json")},
        sort_keys=True,
    )
    return hashlib.sha256(text.encode()).hexdigest()


@dataclass
class Performed:
    response: str  # the JSON answered (stored with the event)
    queued: list[int]  # sessions with newly queued learner updates


def perform(
    server: ServerState,
    token: str | None,
    kind: str,
    body: SeqRequest,
    handler: Callable[[Action], Any],
    session_id: int | None = None,
) -> Performed:
    """Run ``handler`` for this request in one transaction with its event (module docstring).

    The handler returns a Pydantic response model; an ``ApiError`` it raises rolls everything
    back, so a refused request changes nothing and does not use up its sequence number.
    """
    fingerprint = request_fingerprint(kind, session_id, body)
    db = server.db
    with db.transaction() as c:
        participant = participant_for(c, token, lock=not db.is_sqlite)
        if body.seq != participant.next_seq:
            if body.seq < participant.next_seq:
                stored = c.execute(
                    _STORED_EVENT, {"participant_id": participant.id, "seq": body.seq}
                ).first()
                if stored is not None and stored.request_hash == fingerprint:
                    return Performed(stored.response, [])
                raise ApiError(
                    409,
                    f"sequence number {body.seq} was already used by a different request; "
                    f"the next sequence number is {participant.next_seq}",
                )
            raise ApiError(
                409,
                f"request out of order: sequence number {body.seq}, but the next is "
                f"{participant.next_seq} (an earlier request has not arrived)",
            )
        if participant.status == "returned":
            raise ApiError(
                409,
                "this task was returned and its assignment went to another worker; "
                "to take part, accept the task again",
            )
        now = utcnow()
        reactivate(c, participant, now)
        event: dict[str, Any] = {
            "participant_id": participant.id,
            "session_id": session_id,
            "seq": body.seq,
            "kind": kind,
            "created_at": now,
            "request_hash": fingerprint,
        }
        participant.next_seq = body.seq + 1
        participant.last_seen_at = now
        action = Action(c, participant, event, server, now)
        response = handler(action).model_dump_json()
        event_id = add(c, EVENTS, response=response, **event)
        action.flush()
        for queued in action.updates:
            add(
                c,
                UPDATES,
                session_id=queued.session_id,
                update_index=queued.update_index,
                status="pending",
                through_event_id=event_id,
                episodes=queued.episodes,
                actions=queued.actions,
                queued_at=now,
            )
    return Performed(response, [queued.session_id for queued in action.updates])


# -- consent, sessions and completion ---------------------------------------------------------
def consent(action: Action, agree: bool) -> None:
    participant = action.participant
    if participant.status == "waiting":
        raise ApiError(409, "the study is full at the moment: wait for a place first")
    if participant.status != "arrived":
        raise ApiError(409, f"consent was already answered (status {participant.status})")
    if not agree:
        set_status(action.c, participant, "declined", action.now)
        return
    draws = participant_draws(action.settings.seed, participant.id)
    participant.domain = choose_domain(
        action.c, action.study, action.now, action.settings.active_minutes, draws
    )
    set_status(action.c, participant, "consented", action.now, note=f"domain {participant.domain}")
    create_sessions(action.c, participant, action.study, draws)


def participant_draws(seed: int | None, participant_id: int) -> random.Random:
    """The randomness of a participant's assignment: the system's, or with a seed (the demo)
    drawn from the seed and the participant's number, whatever the order of requests."""
    if seed is None:
        return _random
    return random.Random(f"bam-study {seed} {participant_id}")


def lock_domain_assignment(c: Connection) -> None:
    """Make the rest of this transaction the only domain assignment in progress, so that
    participants consenting at the same moment each count the others.

    PostgreSQL: a transaction-level advisory lock, released at commit; the participant row
    locks of ``perform`` do not span participants. Under READ COMMITTED the count that follows
    sees every assignment committed before the lock was granted. SQLite: a write transaction
    opened with BEGIN IMMEDIATE (``Database.transaction``) already excludes every other writer
    from its first statement, in this process and in any other.
    """
    if c.dialect.name == "postgresql":
        c.execute(_LOCK_DOMAIN_ASSIGNMENT)
    elif c.dialect.name == "sqlite" and not c.get_execution_options().get("sqlite_immediate"):
        raise RuntimeError("domains are assigned in a write transaction (Database.transaction)")


def choose_domain(
    c: Connection,
    study: StudyConfig,
    now: datetime,
    active_minutes: float,
    draws: random.Random,
) -> str:
    """The least-filled domain, counting participants who completed and those in progress who
    were active in the last ``active_minutes`` (abandoned or excluded ones do not hold a place);
    ties at random. Holds the domain assignment until the transaction ends."""
    lock_domain_assignment(c)
    since = now - timedelta(minutes=active_minutes)
    names = [domain.name for domain in study.domains]
    counts = dict.fromkeys(names, 0)
    p = PARTICIPANTS.c
    rows = c.execute(
        select(p.domain, func.count())
        .where(
            p.domain.in_(names),
            p.excluded_at.is_(None),
            or_(
                p.status.in_(("completed", "submitted")),
                and_(p.status.in_(IN_PROGRESS), p.last_seen_at >= since),
            ),
        )
        .group_by(p.domain)
    )
    for name, count in rows:
        counts[name] = count
    fewest = min(counts.values())
    return draws.choice([name for name in names if counts[name] == fewest])


def create_sessions(
    c: Connection, participant: Record, study: StudyConfig, draws: random.Random
) -> None:
    """The participant's learning sessions in order: the tutorial, then each environment's
    agents with the learners in a random order; colours by position."""
    domain = study.domain(str(participant.domain))
    rows: list[dict[str, Any]] = []
    if study.tutorial.enabled:
        rows.append(
            {
                "kind": "tutorial",
                "position": None,
                "environment": domain.tutorial_environment,
                "learner": study.tutorial.learner,
                "colour_name": study.tutorial.colour.name,
                "colour_hex": study.tutorial.colour.hex,
            }
        )
    position = 0
    for environment in domain.environments:
        learners = [study.learners[i % len(study.learners)] for i in range(study.agents)]
        draws.shuffle(learners)
        for learner in learners:
            colour = study.colours[position]
            rows.append(
                {
                    "kind": "study",
                    "position": position,
                    "environment": environment,
                    "learner": learner,
                    "colour_name": colour.name,
                    "colour_hex": colour.hex,
                }
            )
            position += 1
    for ordinal, row in enumerate(rows):
        add(
            c,
            SESSIONS,
            participant_id=participant.id,
            ordinal=ordinal,
            domain=domain.name,
            seed=draws.randrange(2**31),
            demonstrated=[],
            **row,
        )


def start(action: Action) -> Record:
    """After consent and the instructions: the first learning session begins."""
    participant = action.participant
    if participant.status != "consented":
        raise ApiError(409, f"cannot start now (status {participant.status})")
    first = _next_session(action.c, participant.id, -1)
    if first is None:
        raise ApiError(409, "this participant has no learning sessions")
    activate(action, first)
    first.opened_at = action.now  # the instructions were its introduction
    return first


def _next_session(c: Connection, participant_id: int, after: int) -> Record | None:
    sessions = load_all(
        c,
        SESSIONS,
        SESSIONS.c.participant_id == participant_id,
        SESSIONS.c.ordinal > after,
        order_by=SESSIONS.c.ordinal,
    )
    return sessions[0] if sessions else None


def activate(action: Action, session: Record) -> None:
    """The session becomes the one being taught; its untrained learner is prepared (update 0)."""
    env = make_environment(session.environment)
    session.status = "active"
    session.started_at = action.now
    session.task = 0
    session.mode = "idle"
    session.state = initial_state(session)
    session.demonstrated = [0] * len(env.tasks)
    session.updates_requested = 0
    action.track(session)
    action.queue_update(session)
    status = "tutorial" if session.kind == "tutorial" else "teaching"
    if action.participant.status != status:
        set_status(action.c, action.participant, status, action.now)


def initial_state(session: Any) -> int:
    """Where the agent starts: a random start of the first task, from the session's seed."""
    env = make_environment(session.environment)
    return random_start(env.name, 0, np.random.default_rng([session.seed, 0]))


@cache
def _start_distribution(environment: str, task: int) -> np.ndarray:
    env = make_environment(environment)
    chosen = env.tasks[task]
    start = np.where(chosen.reward > 0, 0.0, chosen.study_start_distribution)
    return start / start.sum()


def random_start(environment: str, task: int, rng: Any) -> int:
    """A random start of ``task``: the study's start distribution without the task's goal. A
    start on the goal would give an episode with nothing to do (an agent's try from there ends
    at once, and its update would count as an episode)."""
    start = _start_distribution(environment, task)
    return int(rng.choice(len(start), p=start))


def advance(action: Action, finished: Record) -> Record | None:
    """After ``finished``: the next session begins, or the questionnaire (if the study has
    one), or the participant has completed."""
    following = _next_session(action.c, action.participant.id, finished.ordinal)
    if following is not None:
        activate(action, following)
        return following
    if action.study.questionnaire.questions:
        set_status(action.c, action.participant, "questionnaire", action.now)
    else:
        complete(action)
    return None


def answer_questionnaire(action: Action, answers: dict[str, int | str]) -> None:
    """Store the answers to the post-study questionnaire (all of them valid, every required
    question answered: 422 otherwise, nothing stored), then the participant has completed."""
    status = action.participant.status
    if status != "questionnaire":
        raise ApiError(409, f"the questionnaire is not being answered now (status {status})")
    questions = {question.id: question for question in action.study.questionnaire.questions}
    unknown = sorted(set(answers) - set(questions))
    if unknown:
        raise InvalidInput(
            ("body", "answers", unknown[0]),
            f"no question {', '.join(map(repr, unknown))} in this questionnaire",
        )
    rows = []
    for question_id, question in questions.items():
        value = answers.get(question_id)
        if isinstance(value, str) and not value.strip():
            value = None
        if value is None:
            if question.required:
                raise InvalidInput(
                    ("body", "answers", question_id), f"question {question_id!r} needs an answer"
                )
            continue
        rows.append(
            {
                "participant_id": action.participant.id,
                "question_id": question_id,
                "kind": question.kind,
                "question": question.text,
                "answered_at": action.now,
                **checked_answer(question, value),
            }
        )
    for row in rows:
        add(action.c, ANSWERS, **row)
    complete(action)


def checked_answer(question: Question, value: int | str) -> dict[str, str | None]:
    """The answer's ``answer`` and ``label`` columns; 422 for an answer the question does not
    take."""
    loc = ("body", "answers", question.id)
    where = f"question {question.id!r}"
    if isinstance(question, TextQuestion):
        if not isinstance(value, str):
            raise InvalidInput(loc, f"{where} takes text")
        if len(value) > question.max_length:
            raise InvalidInput(loc, f"{where}: at most {question.max_length} characters")
        return {"answer": value, "label": None}
    if isinstance(question, LikertQuestion):
        points = len(question.labels)
        if not isinstance(value, int) or not 1 <= value <= points:
            raise InvalidInput(loc, f"{where} takes a point of its scale, 1 to {points}")
        return {"answer": str(value), "label": question.labels[value - 1]}
    if not isinstance(value, str) or value not in question.choices:
        raise InvalidInput(
            loc, f"{where} takes one of its choices: {', '.join(map(repr, question.choices))}"
        )
    return {"answer": value, "label": None}


def complete(action: Action) -> None:
    participant = action.participant
    if action.study.completion.mode == "prolific" and participant.platform == "prolific":
        participant.completion_code = action.study.completion.prolific_code
    else:
        participant.completion_code = "".join(_random.choice(CODE_ALPHABET) for _ in range(10))
    set_status(action.c, participant, "completed", action.now)


def reach_tutorial_step(action: Action, step: int) -> None:
    """The page's tutorial reached ``step``; the step kept never goes back (another tab may be
    behind)."""
    participant = action.participant
    if participant.status != "tutorial":
        raise ApiError(409, f"the tutorial is not in progress (status {participant.status})")
    participant.tutorial_step = max(int(participant.tutorial_step), step)


def open_session(action: Action, session: Record) -> None:
    """The participant began teaching ``session`` (left its introduction page)."""
    if session.opened_at is None:
        session.opened_at = action.now


def submission(action: Action) -> None:
    """The page reports that it sends the participant's submission to the platform."""
    status = action.participant.status
    if status == "submitted":
        raise ApiError(409, "the submission was already recorded")
    if status != "completed":
        raise ApiError(409, f"the study is not completed yet (status {status})")
    set_status(action.c, action.participant, "submitted", action.now)


def completion(participant: Any, study: StudyConfig) -> Completion | None:
    """The completion code and how to hand it in; None until the completion is committed."""
    if participant.status not in ("completed", "submitted") or participant.completion_code is None:
        return None
    code = participant.completion_code
    if participant.platform == "mturk":
        return Completion(
            code=code,
            mode="mturk",
            submit_url=f"{participant.submit_to}/mturk/externalSubmit",
            submit_fields={"assignmentId": str(participant.assignment_id), "completionCode": code},
        )
    if participant.platform == "prolific":
        return Completion(
            code=code, mode="prolific", redirect_url=study.completion.prolific_redirect()
        )
    return Completion(code=code, mode="lab")


# -- views ----------------------------------------------------------------------------------
def current_session_id(c: Connection, participant: Any) -> int | None:
    return c.scalar(
        select(SESSIONS.c.id).where(
            SESSIONS.c.participant_id == participant.id, SESSIONS.c.status == "active"
        )
    )


def brief(participant: Any, study: StudyConfig, session_id: int | None) -> ParticipantBrief:
    return ParticipantBrief(
        status=participant.status,
        current_session_id=session_id,
        next_seq=participant.next_seq,
        completion=completion(participant, study),
    )


def summary(session: Any) -> SessionSummary:
    return SessionSummary(
        session_id=session.id,
        kind=session.kind,
        position=session.position,
        domain=session.domain,
        environment=session.environment,
        colour={"name": session.colour_name, "hex": session.colour_hex},  # type: ignore[arg-type]
        status=session.status,
        opened=session.opened_at is not None,
    )


def participant_state(c: Connection, participant: Any, study: StudyConfig) -> ParticipantState:
    sessions = load_all(
        c, SESSIONS, SESSIONS.c.participant_id == participant.id, order_by=SESSIONS.c.ordinal
    )
    study_sessions = [x for x in sessions if x.kind == "study"]
    reached = [x for x in study_sessions if x.status != "pending"]
    current = next((x.id for x in sessions if x.status == "active"), None)
    return ParticipantState(
        participant_id=participant.id,
        platform=participant.platform,
        status=participant.status,
        domain=participant.domain,
        current_session_id=current,
        next_seq=participant.next_seq,
        completion=completion(participant, study),
        progress=Progress(agent=len(reached), of=len(study_sessions)),
        sessions=[summary(x) for x in sessions],
        tutorial_step=participant.tutorial_step,
    )
