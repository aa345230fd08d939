"""The study's database tables (SQLAlchemy 2 ORM). Alembic migrations in ``migrations/`` are the
only way these tables are created or changed; API responses are the separate Pydantic models in
``schemas.py``.

participants ─< status_changes
             ─< learning_sessions ─< episodes
                                  ─< learner_updates   (one per update: learner state + evaluation)
             ─< events            (append-only, one per acknowledged request, keyed by seq)
             ─< attention_checks   (the instructional attention checks between agents)
             ─< questionnaire_answers
             ─< reviews           (the experimenter's approval or rejection of the submission)
             ─< bonuses
erasures (one per participant erased: no link to any other row, no personal data)

Every table is in this one module, beside the diagram above: the one schema that the
migrations build, read as one.
"""

from __future__ import annotations

from datetime import UTC, datetime

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    MetaData,
    String,
    Text,
    TypeDecorator,
    UniqueConstraint,
)
from sqlalchemy.engine import Dialect
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

from server.app.storage.vocabulary import (
    BonusState,
    CheckStatus,
    Mode,
    ReviewState,
    SessionStatus,
    UpdateStatus,
)

# Autoincrementing 64-bit ids (SQLite only autoincrements INTEGER PRIMARY KEY).
BigId = BigInteger().with_variant(Integer(), "sqlite")

NAMING_CONVENTION = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_N_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


def utcnow() -> datetime:
    return datetime.now(UTC)


class UTCDateTime(TypeDecorator[datetime]):
    """Timezone-aware UTC timestamps on every backend (SQLite stores them naive)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError("naive datetime given to a UTC column")
        value = value.astimezone(UTC)
        return value.replace(tzinfo=None) if dialect.name == "sqlite" else value

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING_CONVENTION)


class Installation(Base):
    """One row, created by the first migration: this database's own random salt."""

    __tablename__ = "installation"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    secret: Mapped[str] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(UTCDateTime())


class Participant(Base):
    __tablename__ = "participants"
    __table_args__ = (
        # Named, as the naming convention's name (the three columns) is longer than PostgreSQL's
        # 63 characters.
        UniqueConstraint(
            "platform",
            "platform_participant_id",
            "platform_submission_id",
            name="uq_participants_platform_ids",
        ),
        Index("ix_participants_platform_participant_id", "platform_participant_id"),
        Index("ix_participants_status_domain", "status", "domain"),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    # SHA-256 of the participant's bearer token; the token itself is never stored.
    token_hash: Mapped[str] = mapped_column(String(64), unique=True)
    platform: Mapped[str] = mapped_column(String(16))  # mturk, prolific or lab
    # The participant's ids on their platform (0019 renamed them from MTurk's words, worker_id,
    # assignment_id and hit_id): MTurk's workerId or Prolific's PROLIFIC_PID, ...
    platform_participant_id: Mapped[str | None] = mapped_column(String(128))
    # ... MTurk's assignmentId or Prolific's SESSION_ID (the submission's id), ...
    platform_submission_id: Mapped[str | None] = mapped_column(String(128))
    # ... and MTurk's hitId or Prolific's STUDY_ID.
    platform_study_id: Mapped[str | None] = mapped_column(String(128))
    submit_to: Mapped[str | None] = mapped_column(String(512))  # turkSubmitTo
    status: Mapped[str] = mapped_column(String(16))  # ParticipantStatus
    domain: Mapped[str | None] = mapped_column(String(32))
    next_seq: Mapped[int] = mapped_column(Integer, default=1)
    completion_code: Mapped[str | None] = mapped_column(String(32))
    # The tutorial's step reached (the page's steps, from 0), so that it continues anywhere.
    tutorial_step: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    # Exclusion is the experimenter's judgement, beside the flow status, which it leaves as is.
    excluded_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    exclusion_reason: Mapped[str | None] = mapped_column(Text)
    # When the platform ids and the completion code were replaced by their
    # pseudonyms (``rights.scrub``); None while they are as the platform gave them.
    identifiers_scrubbed_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    last_seen_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    # The platform's status of the participant's submission, as its status sync keeps it
    # (Prolific's webhook or poll, e.g. RETURNED; None on a platform without one).
    platform_status: Mapped[str | None] = mapped_column(String(24))
    # When that status was true: the event's time (Prolific's X-Timestamp) or the poll's; an
    # older report leaves a newer one as it is.
    platform_status_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    # When the platform completed the submission (Prolific's ``completed_at``: it went to
    # AWAITING REVIEW, which Prolific approves by itself 21 days later).
    platform_completed_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    # When the platform asked the participant to return the submission (Prolific's
    # ``return_requested``: a REQUEST_RETURN code, such as NO_CONSENT).
    platform_return_requested_at: Mapped[datetime | None] = mapped_column(UTCDateTime())


class ParticipantToken(Base):
    """The token of each further browser of a participant (one that arrived again without the
    first's cookie): every browser keeps its own. The first is ``participants.token_hash``."""

    __tablename__ = "participant_tokens"

    # SHA-256 of the token, as for the first.
    token_hash: Mapped[str] = mapped_column(String(64), primary_key=True)
    participant_id: Mapped[int] = mapped_column(ForeignKey("participants.id"), index=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)


class StatusChange(Base):
    __tablename__ = "status_changes"

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    participant_id: Mapped[int] = mapped_column(ForeignKey("participants.id"), index=True)
    status: Mapped[str] = mapped_column(String(16))  # ParticipantStatus or ExclusionMark
    at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    note: Mapped[str | None] = mapped_column(Text)


class LearningSession(Base):
    """One agent taught by one participant in one environment (or the tutorial's agent)."""

    __tablename__ = "learning_sessions"
    __table_args__ = (UniqueConstraint("participant_id", "ordinal"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    participant_id: Mapped[int] = mapped_column(ForeignKey("participants.id"), index=True)
    ordinal: Mapped[int] = mapped_column(Integer)  # order of the participant's sessions
    kind: Mapped[str] = mapped_column(String(16))  # SessionKind
    position: Mapped[int | None] = mapped_column(Integer)  # 0.. among study sessions
    domain: Mapped[str] = mapped_column(String(32))
    environment: Mapped[str] = mapped_column(String(32))
    learner: Mapped[str] = mapped_column(String(32))
    colour_name: Mapped[str] = mapped_column(String(40))
    colour_hex: Mapped[str] = mapped_column(String(7))
    seed: Mapped[int] = mapped_column(BigInteger)
    status: Mapped[str] = mapped_column(String(16), default=SessionStatus.PENDING)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    # When the participant began teaching it, past its introduction page (None: not yet).
    opened_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    completed: Mapped[bool] = mapped_column(Boolean, default=False)
    # The live state of teaching.
    task: Mapped[int] = mapped_column(Integer, default=0)
    mode: Mapped[str] = mapped_column(String(16), default=Mode.IDLE)
    state: Mapped[int | None] = mapped_column(Integer)
    open_episode: Mapped[int | None] = mapped_column(Integer)  # index of the open episode
    episode_actions: Mapped[int] = mapped_column(Integer, default=0)
    last_action: Mapped[str | None] = mapped_column(String(16))  # LastAction
    demonstrated: Mapped[list[int]] = mapped_column(JSON, default=list)  # actions per task
    episodes: Mapped[int] = mapped_column(Integer, default=0)  # episodes ended
    actions: Mapped[int] = mapped_column(Integer, default=0)  # actions in episodes
    idle_moves: Mapped[int] = mapped_column(Integer, default=0)
    updates_requested: Mapped[int] = mapped_column(Integer, default=-1)  # latest index queued
    updates_processed: Mapped[int] = mapped_column(Integer, default=-1)  # latest index finished
    policy_update: Mapped[int | None] = mapped_column(
        Integer
    )  # latest index done: agent acts on it
    # Someone waits for the agent after update ``awaited_update`` since ``awaited_since`` (on
    # any server of the deployment): the update queues of all servers put the session first.
    awaited_since: Mapped[datetime | None] = mapped_column(UTCDateTime())
    awaited_update: Mapped[int | None] = mapped_column(Integer)


class Episode(Base):
    __tablename__ = "episodes"
    __table_args__ = (UniqueConstraint("session_id", "index"),)

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    session_id: Mapped[int] = mapped_column(ForeignKey("learning_sessions.id"))
    index: Mapped[int] = mapped_column(Integer)
    kind: Mapped[str] = mapped_column(String(16))  # EpisodeKind
    task: Mapped[int] = mapped_column(Integer)
    start_state: Mapped[int] = mapped_column(Integer)
    end_state: Mapped[int | None] = mapped_column(Integer)
    started_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    ended_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    end_reason: Mapped[str | None] = mapped_column(String(16))  # EpisodeEnd
    actions: Mapped[int] = mapped_column(Integer, default=0)
    update_index: Mapped[int | None] = mapped_column(Integer)


class Event(Base):
    """One acknowledged participant request, stored in the transaction that answered it.

    ``record`` says what the learner observes from it (a demonstration step, an agent step,
    a transition alone, or feedback on the latest agent step); ``stay_state`` is the outcome of
    the synthetic STAY appended when the event ended a demonstration.
    """

    __tablename__ = "events"
    __table_args__ = (
        UniqueConstraint("participant_id", "seq"),
        Index("ix_events_session_id_id", "session_id", "id"),
    )

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    participant_id: Mapped[int] = mapped_column(ForeignKey("participants.id"))
    session_id: Mapped[int | None] = mapped_column(ForeignKey("learning_sessions.id"))
    seq: Mapped[int] = mapped_column(Integer)
    kind: Mapped[str] = mapped_column(String(24))
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    task: Mapped[int | None] = mapped_column(Integer)
    mode: Mapped[str | None] = mapped_column(String(16))  # Mode
    state: Mapped[int | None] = mapped_column(Integer)
    action: Mapped[int | None] = mapped_column(Integer)
    next_state: Mapped[int | None] = mapped_column(Integer)
    feedback: Mapped[int | None] = mapped_column(Integer)
    episode_index: Mapped[int | None] = mapped_column(Integer)
    record: Mapped[str | None] = mapped_column(String(16))  # Observed
    stay_state: Mapped[int | None] = mapped_column(Integer)
    episode_end: Mapped[str | None] = mapped_column(String(16))  # EpisodeEnd, here
    request_hash: Mapped[str] = mapped_column(String(64))
    response: Mapped[str] = mapped_column(Text)


class LearnerUpdate(Base):
    """A learner update and the evaluation of the policies it produced.

    Index 0 is the untrained learner (no update); index k >= 1 is the update queued when the
    k-th episode ended. ``through_event_id`` is the last event whose data it includes.
    """

    __tablename__ = "learner_updates"
    __table_args__ = (
        UniqueConstraint("session_id", "update_index"),
        Index("ix_learner_updates_status", "status"),
    )

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    session_id: Mapped[int] = mapped_column(ForeignKey("learning_sessions.id"))
    update_index: Mapped[int] = mapped_column(Integer)
    status: Mapped[str] = mapped_column(String(16), default=UpdateStatus.PENDING)
    through_event_id: Mapped[int] = mapped_column(BigInteger, default=0)
    episodes: Mapped[int] = mapped_column(Integer)  # cumulative episodes
    actions: Mapped[int] = mapped_column(Integer)  # cumulative actions
    queued_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    seconds: Mapped[float | None] = mapped_column(Float)
    objective: Mapped[float | None] = mapped_column(Float)
    steps: Mapped[int | None] = mapped_column(Integer)
    normalized_return: Mapped[float | None] = mapped_column(Float)
    evaluation_seconds: Mapped[float | None] = mapped_column(Float)
    learner_state: Mapped[bytes | None] = mapped_column(LargeBinary)
    greedy_policy: Mapped[bytes | None] = mapped_column(LargeBinary)
    error: Mapped[str | None] = mapped_column(Text)
    # The claim on a pending update (``server.app.updates.store``): the server that runs it,
    # until when its lease holds (renewed while it runs; past it, another server takes the
    # update over, ``taken_from`` the server whose lease expired), and ``runs``, the claims
    # taken on it (an update that ran once has 1, whatever ``attempts`` says of retries).
    claimed_by: Mapped[str | None] = mapped_column(String(64))
    lease_until: Mapped[datetime | None] = mapped_column(UTCDateTime())
    runs: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    taken_from: Mapped[str | None] = mapped_column(String(64))


class AttentionCheck(Base):
    """One instructional attention check of a participant (the study file's
    ``[attention_checks]``): made at consent, shown after the study session ``after_ordinal``
    is finished. The participant moves a robot on an open ``size`` x ``size`` grid (cells
    numbered row * size + column) towards the star; the server decides: ``passed`` when the
    star is reached within ``moves_allowed`` moves, ``failed`` when the moves run out. Each
    move is also an event (kind ``attention_move``)."""

    __tablename__ = "attention_checks"
    __table_args__ = (UniqueConstraint("participant_id", "number"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    participant_id: Mapped[int] = mapped_column(ForeignKey("participants.id"), index=True)
    number: Mapped[int] = mapped_column(Integer)  # 0.. in the participant's order
    after_ordinal: Mapped[int] = mapped_column(Integer)  # the session it follows
    size: Mapped[int] = mapped_column(Integer)
    start_cell: Mapped[int] = mapped_column(Integer)
    star_cell: Mapped[int] = mapped_column(Integer)
    moves_allowed: Mapped[int] = mapped_column(Integer)
    status: Mapped[str] = mapped_column(String(16), default=CheckStatus.PENDING)
    cell: Mapped[int] = mapped_column(Integer)  # where the robot is
    moves: Mapped[list[str]] = mapped_column(JSON, default=list)  # the arrows, in order
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime())


class QuestionnaireAnswer(Base):
    """One answer to a question of the post-study questionnaire (the study file's
    ``[questionnaire]``). A question left unanswered (an optional one) has no row. The
    question's kind and text are kept with the answer, as they were asked."""

    __tablename__ = "questionnaire_answers"
    __table_args__ = (UniqueConstraint("participant_id", "question_id"),)

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    participant_id: Mapped[int] = mapped_column(ForeignKey("participants.id"))
    question_id: Mapped[str] = mapped_column(String(64))
    kind: Mapped[str] = mapped_column(String(16))  # text, likert or choice
    question: Mapped[str] = mapped_column(Text)
    # The text typed, the choice picked, or the Likert point (1 to the scale's length).
    answer: Mapped[str] = mapped_column(Text)
    # Likert: the label of the point picked.
    label: Mapped[str | None] = mapped_column(Text)
    answered_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)


class Review(Base):
    """The experimenter's decision on a participant's submitted work (an MTurk assignment or a
    Prolific submission): one per participant, final. The row is written as ``pending`` before
    the platform is called and becomes ``done`` once the platform has taken the decision, so
    that a decision the platform carried out is never missing here (``platforms/review/``)."""

    __tablename__ = "reviews"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    participant_id: Mapped[int] = mapped_column(ForeignKey("participants.id"), unique=True)
    # The MTurk assignmentId or the Prolific submission id (SESSION_ID).
    platform_submission_id: Mapped[str] = mapped_column(String(128), unique=True)
    platform_participant_id: Mapped[str] = mapped_column(String(128))  # workerId or PROLIFIC_PID
    decision: Mapped[str] = mapped_column(String(16))  # ReviewDecision
    message: Mapped[str | None] = mapped_column(Text)  # shown to the participant
    rejection_category: Mapped[str | None] = mapped_column(String(32))  # Prolific's category
    backend: Mapped[str] = mapped_column(String(24))  # mturk, mturk-replica, prolific, ...
    state: Mapped[str] = mapped_column(String(16), default=ReviewState.DONE)
    requested_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    decided_at: Mapped[datetime | None] = mapped_column(UTCDateTime())


class Bonus(Base):
    """A bonus for a participant's submitted work. The row is written before the platform is
    called (``pending``, with ``unique_token``, sent as MTurk's UniqueRequestToken); on Prolific
    the bonus's set-up id is stored (``set_up``) before the one ``pay`` call (``paying``, at
    ``pay_sent_at``), so that neither a retry nor a crash pays twice; ``paid`` once the platform
    took it; ``in_doubt`` when the outcome is not known (Prolific's pay failed after it may have
    paid: settled from the submission's ``bonus_payments``)."""

    __tablename__ = "bonuses"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    participant_id: Mapped[int] = mapped_column(ForeignKey("participants.id"), index=True)
    platform_submission_id: Mapped[str] = mapped_column(String(128))
    platform_participant_id: Mapped[str] = mapped_column(String(128))
    amount_cents: Mapped[int] = mapped_column(Integer)  # cents of ``currency``
    currency: Mapped[str] = mapped_column(String(3), default="USD")
    reason: Mapped[str] = mapped_column(Text)  # shown to the participant
    unique_token: Mapped[str] = mapped_column(String(64), unique=True)
    backend: Mapped[str] = mapped_column(String(24))
    state: Mapped[str] = mapped_column(String(16), default=BonusState.PAID)
    setup_id: Mapped[str | None] = mapped_column(String(64))  # Prolific's bulk bonus payment id
    requested_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    pay_sent_at: Mapped[datetime | None] = mapped_column(UTCDateTime())  # Prolific's pay sent
    paid_at: Mapped[datetime | None] = mapped_column(UTCDateTime())


class Message(Base):
    """A message sent to a participant through Prolific's messages API (``bam-study prolific
    message``), one row per recipient, written once Prolific took it: a message it refused is
    not stored."""

    __tablename__ = "messages"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    participant_id: Mapped[int] = mapped_column(ForeignKey("participants.id"), index=True)
    platform_participant_id: Mapped[str] = mapped_column(
        String(128)
    )  # the recipient's PROLIFIC_PID
    study_id: Mapped[str] = mapped_column(String(128))  # the STUDY_ID the message is about
    body: Mapped[str] = mapped_column(Text)
    backend: Mapped[str] = mapped_column(String(24))  # prolific or prolific-replica
    # Prolific's call (messages: one recipient; messages/bulk: several) and its answer (204).
    sent_with: Mapped[str] = mapped_column(String(32))
    answer_status: Mapped[int] = mapped_column(Integer)
    sent_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)


class ProlificEvent(Base):
    """A Prolific webhook event applied (``X-Event-ID``): delivery is at-least-once, so each
    event is applied once."""

    __tablename__ = "prolific_events"

    event_id: Mapped[str] = mapped_column(String(128), primary_key=True)
    event_type: Mapped[str] = mapped_column(String(64))
    received_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)


class ProlificStudy(Base):
    """What Prolific's study events said of a study (``study.status.change``,
    ``study.has_high_return_rate``): its status and when it took it (the event's
    ``X-Timestamp``, so an older event arriving late leaves a newer status), and the last
    high-return-rate warning with the event's ``metadata`` as Prolific sent it."""

    __tablename__ = "prolific_studies"

    study_id: Mapped[str] = mapped_column(String(64), primary_key=True)
    status: Mapped[str | None] = mapped_column(String(24))
    status_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    high_return_rate_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    high_return_rate_metadata: Mapped[dict[str, object] | None] = mapped_column(JSON)


class ProlificWebhookSecret(Base):
    """A Prolific workspace's webhook signing secret, as ``POST /hooks/secrets/`` gave it to
    ``bam-study prolific hooks`` (one per workspace: a new one replaces the old, on Prolific
    and here); ``/prolific/webhook`` accepts events signed with it."""

    __tablename__ = "prolific_webhook_secrets"

    workspace_id: Mapped[str] = mapped_column(String(64), primary_key=True)
    secret: Mapped[str] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)


class ProlificStudyChange(Base):
    """A change the server made to its Prolific study by itself (``prolific_capacity``): its
    ``max_concurrent_submissions`` set to the server's live capacity, or the study paused while
    the update queue would make agents wait and started when it drained; with why, and
    Prolific's answer (``done``, or its refusal)."""

    __tablename__ = "prolific_study_changes"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    study_id: Mapped[str] = mapped_column(String(64), index=True)
    at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    change: Mapped[str] = mapped_column(String(32))  # max_concurrent_submissions, PAUSE, START
    value: Mapped[int | None] = mapped_column(Integer)  # the new max_concurrent_submissions
    reason: Mapped[str] = mapped_column(Text)
    outcome: Mapped[str] = mapped_column(Text)  # done, or why Prolific refused


# The deployment's own tables: its servers and their jobs, the experimenter's sign-ins. No row
# of them is a participant's; the servers write them while they run (heartbeats).
DEPLOYMENT_TABLES = ("servers", "periodic_runs", "admin_sessions", "sign_in_failures")


class Erasure(Base):
    """The audit row of one participant's erasure (``rights.erasure``): when, by whom, the
    participant's pseudonyms and how many rows each table lost; nothing else of theirs is
    left. ``participant_id`` refers to no row any more (the participant's row is erased too)."""

    __tablename__ = "erasures"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    erased_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    erased_by: Mapped[str] = mapped_column(String(16))  # ErasedBy
    participant_id: Mapped[int] = mapped_column(Integer)
    platform: Mapped[str] = mapped_column(String(16))
    platform_participant_pseudonym: Mapped[str | None] = mapped_column(
        String(32)
    )  # w_ + salted hash
    platform_submission_pseudonym: Mapped[str | None] = mapped_column(
        String(32)
    )  # a_ + salted hash
    rows: Mapped[dict[str, int]] = mapped_column(JSON)  # table -> rows removed


class StudyServer(Base):
    """One ``bam-study serve`` process of the deployment (``server.app.updates.servers``): its
    name, where it runs, when it started, its latest heartbeat with its load then, and when it
    stopped (None: running, or it died and its heartbeat stopped)."""

    __tablename__ = "servers"

    name: Mapped[str] = mapped_column(String(64), primary_key=True)
    host: Mapped[str] = mapped_column(String(255))
    pid: Mapped[int] = mapped_column(Integer)
    started_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    heartbeat_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    stopped_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    update_slots: Mapped[int] = mapped_column(Integer, default=0)
    updates_running: Mapped[int] = mapped_column(Integer, default=0)
    updates_completed: Mapped[int] = mapped_column(Integer, default=0)
    updates_failed: Mapped[int] = mapped_column(Integer, default=0)
    participants_at_once: Mapped[int | None] = mapped_column(Integer)  # its capacity
    # What the deployment's capacity is summed from (``server.app.updates.capacity``): where its
    # update slots run (``servers.slots_machine``: servers with the same share its cores), the
    # cores they share with the server's process there (None: a cluster's workers), and the
    # costs of an update its capacity was stated from (None: not yet timed).
    machine: Mapped[str] = mapped_column(String(255), default="", server_default="")
    cores: Mapped[int | None] = mapped_column(Integer)
    update_seconds: Mapped[float | None] = mapped_column(Float)
    server_seconds: Mapped[float | None] = mapped_column(Float)


class DashboardSession(Base):
    """A signed-in dashboard (``server.app.admin_auth``): the sha256 of its random id, and its
    expiry in seconds since the epoch (as its cookie says). In the database, so that a cookie
    one server gave works on every server of the deployment."""

    __tablename__ = "admin_sessions"

    id_hash: Mapped[str] = mapped_column(String(64), primary_key=True)
    expires: Mapped[int] = mapped_column(BigInteger, index=True)


class SignInFailure(Base):
    """A failed sign-in (a wrong admin token) from a client address, at ``failed_at`` seconds
    since the epoch: counted across every server of the deployment."""

    __tablename__ = "sign_in_failures"
    __table_args__ = (Index("ix_sign_in_failures_address", "address", "failed_at"),)

    id: Mapped[int] = mapped_column(BigId, primary_key=True)
    address: Mapped[str] = mapped_column(String(64))
    failed_at: Mapped[float] = mapped_column(Float, index=True)


class PeriodicRun(Base):
    """The latest run of a periodic job (time-outs, scrubbing) by whichever server ran it: the
    servers of a deployment run each job once per period between them."""

    __tablename__ = "periodic_runs"

    job: Mapped[str] = mapped_column(String(64), primary_key=True)
    ran_at: Mapped[datetime] = mapped_column(UTCDateTime())
    ran_by: Mapped[str] = mapped_column(String(64))
