"""Consent, the balanced assignment of domains, and the order of a participant's learning
sessions.
"""

from __future__ import annotations

import random
from datetime import datetime, timedelta
from functools import cache
from typing import Any

import numpy as np
from sqlalchemy import Connection, and_, func, or_, select

from server.app.errors import ApiError
from server.app.participants import tokens
from server.app.participants.completion import complete
from server.app.participants.statuses import set_status
from server.app.participants.transaction import Transaction
from server.app.storage.db import advisory_lock_key
from server.app.storage.records import Record, add, load, load_all
from server.app.storage.tables import CHECKS, PARTICIPANTS, SESSIONS
from server.app.storage.vocabulary import (
    FINISHED_STATUSES,
    IN_PROGRESS,
    CheckStatus,
    Mode,
    ParticipantStatus,
    SessionKind,
    SessionStatus,
)
from server.app.study_file import AttentionChecks, StudyConfig
from server.domains import make as make_environment

DOMAIN_LOCK_KEY = advisory_lock_key("bam-study domain assignment")
LOCK_DOMAIN_ASSIGNMENT = select(func.pg_advisory_xact_lock(DOMAIN_LOCK_KEY))


def consent(transaction: Transaction, agree: bool) -> None:
    participant = transaction.participant
    if participant.status == ParticipantStatus.WAITING:
        raise ApiError(409, "the study is full at the moment: wait for a place first")
    if participant.status != ParticipantStatus.ARRIVED:
        raise ApiError(409, f"consent was already answered (status {participant.status})")
    if not agree:
        set_status(transaction.c, participant, ParticipantStatus.DECLINED, transaction.now)
        return
    draws = participant_draws(transaction.settings.seed, participant.id)
    participant.domain = choose_domain(
        transaction.c,
        transaction.study,
        transaction.now,
        transaction.settings.active_minutes,
        draws,
    )
    set_status(
        transaction.c,
        participant,
        ParticipantStatus.CONSENTED,
        transaction.now,
        note=f"domain {participant.domain}",
    )
    create_sessions(transaction.c, participant, transaction.study, draws)


def participant_draws(seed: int | None, participant_id: int) -> random.Random:
    """The randomness of a participant's assignment: the system's, or with a seed (the demo)
    drawn from the seed and the participant's number, whatever the order of requests."""
    if seed is None:
        return tokens.SYSTEM_RANDOM
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
        c.execute(LOCK_DOMAIN_ASSIGNMENT)
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
                p.status.in_(FINISHED_STATUSES),
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
                "kind": SessionKind.TUTORIAL,
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
                    "kind": SessionKind.STUDY,
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
    # The checks are drawn after the sessions, which stay as they are without checks.
    ordinal_of = {row["position"]: ordinal for ordinal, row in enumerate(rows)}
    checks = study.attention_checks
    for number, after in enumerate(checks.after_agents(position)):
        start, star = draw_check_cells(checks, draws)
        add(
            c,
            CHECKS,
            participant_id=participant.id,
            number=number,
            after_ordinal=ordinal_of[after],
            size=checks.size,
            start_cell=start,
            star_cell=star,
            moves_allowed=checks.moves,
            status=CheckStatus.PENDING,
            cell=start,
            moves=[],
        )


def draw_check_cells(checks: AttentionChecks, draws: random.Random) -> tuple[int, int]:
    """The robot's and the star's cells (row * size + column) of one attention check: as the
    study file fixes them, or drawn, at least size - 1 moves apart."""
    n = checks.size
    cells = [(row, column) for row in range(n) for column in range(n)]

    def far_from(cell: tuple[int, int]) -> list[tuple[int, int]]:
        return [x for x in cells if abs(x[0] - cell[0]) + abs(x[1] - cell[1]) >= n - 1]

    start, star = _fixed(checks.start), _fixed(checks.star)
    if start is None:
        start = draws.choice(cells if star is None else far_from(star))
    if star is None:
        star = draws.choice(far_from(start))
    return start[0] * n + start[1], star[0] * n + star[1]


def _fixed(cell: tuple[int, int] | str) -> tuple[int, int] | None:
    return None if isinstance(cell, str) else (cell[0], cell[1])


def start(transaction: Transaction) -> Record:
    """After consent and the instructions: the first learning session begins."""
    participant = transaction.participant
    if participant.status != ParticipantStatus.CONSENTED:
        raise ApiError(409, f"cannot start now (status {participant.status})")
    first = _next_session(transaction.c, participant.id, -1)
    if first is None:
        raise ApiError(409, "this participant has no learning sessions")
    activate(transaction, first)
    first.opened_at = transaction.now  # the instructions were its introduction
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


def activate(transaction: Transaction, session: Record) -> None:
    """The session becomes the one being taught; its untrained learner is prepared (update 0)."""
    env = make_environment(session.environment)
    session.status = SessionStatus.ACTIVE
    session.started_at = transaction.now
    session.task = 0
    session.mode = Mode.IDLE
    session.state = initial_state(session)
    session.demonstrated = [0] * len(env.tasks)
    session.updates_requested = 0
    transaction.track(session)
    transaction.queue_update(session)
    status = (
        ParticipantStatus.TUTORIAL
        if session.kind == SessionKind.TUTORIAL
        else ParticipantStatus.TEACHING
    )
    if transaction.participant.status != status:
        set_status(transaction.c, transaction.participant, status, transaction.now)


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


def advance(transaction: Transaction, finished: Record) -> Record | None:
    """After ``finished``: its attention check (if it has one) begins, or the next session, or
    the questionnaire (if the study has one), or the participant has completed."""
    check = load(
        transaction.c,
        CHECKS,
        CHECKS.c.participant_id == transaction.participant.id,
        CHECKS.c.after_ordinal == finished.ordinal,
        CHECKS.c.status == CheckStatus.PENDING,
    )
    if check is not None:
        check.status = CheckStatus.ACTIVE
        check.started_at = transaction.now
        transaction.track(check)
        return None
    return continue_after(transaction, finished.ordinal)


def continue_after(transaction: Transaction, ordinal: int) -> Record | None:
    """The session after ``ordinal`` begins, or the questionnaire, or the completion."""
    following = _next_session(transaction.c, transaction.participant.id, ordinal)
    if following is not None:
        activate(transaction, following)
        return following
    if transaction.study.questionnaire.questions:
        set_status(
            transaction.c, transaction.participant, ParticipantStatus.QUESTIONNAIRE, transaction.now
        )
    else:
        complete(transaction)
    return None
