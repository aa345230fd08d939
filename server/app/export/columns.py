"""The export's files and columns as data: each file is a tuple of ``Column``s, in the CSV's
order, and each column carries its description (the data dictionary), its kind and how its
value is read from a row. ``DICTIONARY``, ``INTEGER_COLUMNS`` and ``TUTORIAL_SESSIONS`` (the
study sessions' columns but ``position``) are derived from the tuples, so that no column is
written undescribed and a value read from a field that is not there raises instead of leaving
the column empty.

Every file's columns are here, one after the other in the data dictionary's order, so that the
dictionary reads as one page: about 150 columns, most of the module's lines.

A column's value is ``value(row, context)`` (``export.read.Context``), or the row's attribute of
the column's name when ``value`` is not given; a ``time`` value is written in ISO 8601.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

from server.app.export import quality
from server.app.export.read import Context
from server.app.rights.pseudonyms import ASSIGNMENT, WORKER
from server.app.storage.vocabulary import ParticipantStatus, SessionKind
from server.domains import make as make_environment
from server.domains.base import ACTIONS
from server.names import learner_names_prose

Kind = Literal["int", "number", "bool", "time", "text"]
INT: Kind = "int"  # an integer, its empty cells empty (pandas' Int64, no decimal point)
NUMBER: Kind = "number"
BOOL: Kind = "bool"
TIME: Kind = "time"  # UTC, ISO 8601


@dataclass(frozen=True)
class Column:
    """One exported column: its name, its description and kind, and its value for a row."""

    name: str
    description: str
    kind: Kind = "text"
    value: Callable[[Any, Context], Any] | None = None  # None: the row's attribute ``name``

    def read(self, row: Any, context: Context) -> Any:
        """The column's cell for ``row``; raises (``AttributeError``, ``KeyError``) when the
        value reads a field that is not there."""
        value = getattr(row, self.name) if self.value is None else self.value(row, context)
        if self.kind == TIME and value is not None:
            return value.isoformat()
        return value


# The first time of each status, in the vocabulary's order (waiting has no column).
STATUS_COLUMNS = tuple(s for s in ParticipantStatus if s is not ParticipantStatus.WAITING)


def _pseudonymised(name: str, prefix: str, description: str, owner: str) -> Column:
    """A worker or assignment id, as ``Context.platform_id`` exports it; ``owner``: the row's
    field that holds the participant's number."""
    return Column(
        name,
        description,
        value=lambda row, ctx: ctx.platform_id(getattr(row, name), prefix, getattr(row, owner)),
    )


def _first(status: str) -> Column:
    return Column(
        f"{status}_at",
        f"First time the participant's status became {status} (UTC, ISO 8601).",
        TIME,
        lambda p, ctx: ctx.first(p.id, status),
    )


def _figure(name: str, description: str, kind: Kind) -> Column:
    return Column(name, description, kind, lambda p, ctx: getattr(ctx.figures[p.id], name))


PARTICIPANTS = (
    Column("participant_id", "Participant number (database id).", INT, lambda p, ctx: p.id),
    Column("platform", "mturk, prolific or lab."),
    _pseudonymised(
        "platform_participant_id",
        WORKER,
        "MTurk workerId or Prolific PROLIFIC_PID (pseudonymised: w_ + salted hash; formerly "
        "worker_id).",
        owner="id",
    ),
    _pseudonymised(
        "platform_submission_id",
        ASSIGNMENT,
        "MTurk assignmentId or Prolific SESSION_ID (pseudonymised: a_ + hash; formerly "
        "assignment_id).",
        owner="id",
    ),
    Column("platform_study_id", "MTurk hitId or Prolific STUDY_ID (formerly hit_id)."),
    Column(
        "status",
        "Latest status: arrived, incompatible (turned away by the device check before "
        "consent; why: status_changes.csv's note), consented, declined, tutorial, teaching, "
        "questionnaire (answering the post-study questionnaire), completed, submitted, returned "
        "(MTurk HIT returned, or Prolific submission RETURNED or TIMED-OUT: released) or "
        "abandoned (idle too long).",
    ),
    Column(
        "prolific_status",
        "Prolific's latest status of the participant's submission (ACTIVE, "
        "AWAITING REVIEW, APPROVED, REJECTED, RETURNED, TIMED-OUT and the others), from its "
        "webhook or a poll; empty for other platforms or when not yet known.",
        value=lambda p, ctx: p.platform_status,
    ),
    Column(
        "prolific_completed_at",
        "When Prolific completed the submission (UTC): it went to AWAITING REVIEW, which Prolific "
        "approves and pays by itself 21 days later unless it is reviewed or returned first; "
        "Prolific's completed_at from a poll, else the webhook's event time.",
        TIME,
        lambda p, ctx: p.platform_completed_at,
    ),
    Column(
        "prolific_return_requested_at",
        "When Prolific asked the participant to return the submission (UTC): a completion code "
        "with REQUEST_RETURN, such as NO_CONSENT (a decliner); returned only if prolific_status "
        "is RETURNED. Empty when no return was asked for.",
        TIME,
        lambda p, ctx: p.platform_return_requested_at,
    ),
    Column("domain", "Domain assigned at consent (empty before)."),
    Column(
        "excluded",
        "True if the experimenter excluded the participant from analysis.",
        BOOL,
        lambda p, ctx: p.excluded_at is not None,
    ),
    Column("exclusion_reason", "The experimenter's reason for the exclusion."),
    *(_first(status) for status in STATUS_COLUMNS),
    Column("excluded_at", "When the participant was excluded (UTC).", TIME),
    Column("last_seen_at", "The participant's latest request that changed something (UTC).", TIME),
    _figure(
        "minutes",
        "Minutes from arrival to completion (or to the latest request if not completed).",
        NUMBER,
    ),
    _figure("agents", "Study agents (learning sessions) assigned.", INT),
    _figure("agents_finished", "Study agents the participant finished.", INT),
    Column("tutorial_step", "The tutorial step the participant reached (from 0).", INT),
    Column(
        "completion_code",
        "The completion code issued (left out when pseudonymised).",
        value=lambda p, ctx: None if ctx.pseudonymize else p.completion_code,
    ),
)


def _counted(name: str, description: str, kind: Kind = INT) -> Column:
    """A figure of ``read.SessionCounts``."""
    return Column(name, description, kind, lambda x, ctx: getattr(ctx.counts(x.id), name))


SESSIONS = (
    Column(
        "session_id",
        "Learning session number (database id): one agent taught by one participant.",
        INT,
        lambda x, ctx: x.id,
    ),
    Column("participant_id", "The participant (participants.csv).", INT),
    Column("domain", "navigation, farming or gravity."),
    Column("environment", "The environment taught."),
    Column("learner", f"The agent's learning algorithm ({learner_names_prose()})."),
    Column("position", "Order among the participant's study agents, from 0.", INT),
    Column("started_at", "When this agent's turn came (UTC).", TIME),
    Column("finished_at", "When the participant finished this agent (UTC; empty if not).", TIME),
    Column(
        "completed",
        "True if the participant finished teaching this agent.",
        BOOL,
        lambda x, ctx: bool(x.completed),
    ),
    Column(
        "opened_at",
        "When the participant began teaching it, past its introduction page (UTC).",
        TIME,
    ),
    Column("colour", "The agent's colour on screen.", value=lambda x, ctx: x.colour_name),
    Column("seed", "Seed of the session's learner and of its random starts and dynamics.", INT),
    Column("episodes", "Episodes ended (demonstrations plus agent episodes).", INT),
    _counted("demonstrations", "Demonstration episodes ended."),
    _counted("agent_episodes", "Agent episodes ended."),
    Column(
        "actions",
        "Actions in episodes (demonstrated plus agent actions; no synthetic STAY).",
        INT,
    ),
    _counted("demonstrated_actions", "Demonstrated actions (teacher moves in demonstrate mode)."),
    _counted("agent_actions", "Actions the agent took on its own."),
    Column(
        "idle_moves",
        "Moves in idle mode (not demonstrations; their transitions are observed).",
        INT,
    ),
    _counted("feedback_given", "Feedback signals given (+ or -)."),
    _counted(
        "updates",
        "Learner updates after episodes processed (update 0, the untrained learner's "
        "evaluation, is not one; the API's `learning.updates` counts the same).",
    ),
    _counted(
        "final_normalized_return",
        "Normalised return after the session's last processed update.",
        NUMBER,
    ),
)
TUTORIAL_SESSIONS = tuple(column for column in SESSIONS if column.name != "position")


# The column that names an episode's or an event's learning session, by the session's kind: a
# study session is a row of sessions.csv, a tutorial's a row of tutorial_sessions.csv, so that
# each column is a foreign key into one file (the ids are one sequence: one of the two is set).
SESSION_COLUMNS = {SessionKind.STUDY: "session_id", SessionKind.TUTORIAL: "tutorial_session_id"}


def _session_of_kind(kind: SessionKind, description: str) -> Column:
    """The row's learning session if it is of ``kind``, else empty (and for an event outside
    any session)."""

    def value(row: Any, ctx: Context) -> int | None:
        if row.session_id is None or ctx.session(row.session_id).kind != kind:
            return None
        return int(row.session_id)

    return Column(SESSION_COLUMNS[kind], description, INT, value)


def _task_name(e: Any, ctx: Context) -> str:
    return make_environment(ctx.session(e.session_id).environment).tasks[e.task].name


EPISODES = (
    Column("episode_id", "Episode number (database id).", INT, lambda e, ctx: e.id),
    _session_of_kind(
        SessionKind.STUDY,
        "The learning session (sessions.csv); empty for a tutorial's episode.",
    ),
    _session_of_kind(
        SessionKind.TUTORIAL,
        "The tutorial's learning session (tutorial_sessions.csv); empty for a study session's "
        "episode.",
    ),
    Column(
        "participant_id",
        "The participant.",
        INT,
        lambda e, ctx: ctx.session(e.session_id).participant_id,
    ),
    Column(
        "session_kind",
        "study (session_id is given) or tutorial (tutorial_session_id is).",
        value=lambda e, ctx: ctx.session(e.session_id).kind,
    ),
    Column("index", "Order of the episode in its session, from 0.", INT),
    Column("kind", "demonstration or agent."),
    Column("task", "Index of the task selected during the episode.", INT),
    Column("task_name", "Name of that task.", value=_task_name),
    Column(
        "start_state",
        "State before the episode's first action (never the task's goal in "
        "data recorded since no episode may start there; before, a demonstration's start_state "
        "was the state after its first move).",
        INT,
    ),
    Column("end_state", "State when it ended (after the synthetic STAY, if any).", INT),
    Column("started_at", "Time of the first action (UTC).", TIME),
    Column("ended_at", "When it ended (UTC; empty if still open).", TIME),
    Column(
        "end_reason",
        "end (the participant), goal, horizon (agent episodes), or implicitly: "
        "task, mode, reset, finish.",
    ),
    Column("actions", "Actions in the episode (no synthetic STAY).", INT),
    Column("update_index", "The learner update queued when it ended (evaluations.csv).", INT),
)

EVENTS = (
    Column("event_id", "Event number (database id; increasing in time).", INT, lambda e, c: e.id),
    Column("participant_id", "The participant.", INT),
    _session_of_kind(
        SessionKind.STUDY,
        "The learning session (sessions.csv); empty for a tutorial's events (tutorial_session_id) "
        "and for device_check, consent, start, tutorial, submission and attention_move.",
    ),
    _session_of_kind(
        SessionKind.TUTORIAL,
        "The tutorial's learning session (tutorial_sessions.csv); empty for every other event.",
    ),
    Column("seq", "The participant's sequence number of the request.", INT),
    Column(
        "kind",
        "device_check (the device check passed or failed before consent), "
        "consent, start, tutorial (a tutorial step reached), submission, open (teaching "
        "begun after the agent's introduction page), task, mode, move, agent_step, feedback, "
        "reset, end_episode, finish, or attention_move (a move in an attention check: state "
        "and next_state are its grid's cells, row x size + column).",
    ),
    Column("created_at", "When the request was committed (UTC).", TIME),
    Column("task", "Task selected (for task: the new one).", INT),
    Column("mode", "Mode after the event: idle, demonstrate or agent."),
    Column("state", "The agent's state before the event.", INT),
    Column(
        "action",
        "The action taken (move, agent_step): STAY, UP, DOWN, LEFT or RIGHT.",
        value=lambda e, ctx: ACTIONS[e.action] if e.action is not None else None,
    ),
    Column(
        "next_state",
        "The agent's state after the event (before a synthetic STAY); differs "
        "from state for a mode or task event when the agent stood on the selected task's goal "
        "with a mode on and was put at a random start.",
        INT,
    ),
    Column("feedback", "+1 or -1 (feedback events); 0 on agent steps.", INT),
    Column("episode_index", "The episode the event belongs to or ended.", INT),
    Column(
        "record",
        "What the learner observed: demonstration, agent_step, transition (idle move) "
        "or feedback (on the latest agent step).",
    ),
    Column(
        "stay_state",
        "Outcome of the synthetic STAY appended to a demonstration that ended here.",
        INT,
    ),
    Column("episode_end", "Why an episode ended at this event (see episodes.csv end_reason)."),
)


def _of_session(name: str, description: str, kind: Kind = "text") -> Column:
    """A field of the update's learning session."""
    return Column(name, description, kind, lambda u, ctx: getattr(ctx.session(u.session_id), name))


EVALUATIONS = (
    Column("session_id", "The learning session (sessions.csv).", INT),
    _of_session("participant_id", "The participant.", INT),
    _of_session("domain", "The session's domain."),
    _of_session("environment", "The session's environment."),
    _of_session("learner", "The session's learner."),
    _of_session("position", "The session's position.", INT),
    Column(
        "update_index",
        "0: the untrained learner; k >= 1: the update after the k-th episode.",
        INT,
    ),
    Column(
        "episodes",
        "Episodes ended in the session when the update was queued (cumulative).",
        INT,
    ),
    Column("actions", "Actions in the session's episodes by then (cumulative).", INT),
    Column(
        "normalized_return",
        "Exact expected total return of the agent's greedy policies over all "
        "tasks divided by the optimal total return (empty if the update failed).",
        NUMBER,
    ),
    Column(
        "status",
        "done, or failed (the update raised an error; the next one includes its data).",
    ),
    Column("objective", "The learner's objective after the update.", NUMBER),
    Column(
        "update_seconds",
        "Time the learner update took.",
        NUMBER,
        lambda u, ctx: u.seconds,
    ),
    Column("queued_at", "When the episode ended and the update was queued (UTC).", TIME),
    Column("finished_at", "When the update and its evaluation were committed (UTC).", TIME),
)

STATUS_CHANGES = (
    Column("participant_id", "The participant.", INT),
    Column("status", "The new status, or excluded / included (the experimenter's marks)."),
    Column("at", "When (UTC).", TIME),
    Column("note", "Details (the session begun, the reason for an exclusion, ...)."),
)

QUESTIONNAIRE_ANSWERS = (
    Column("participant_id", "The participant.", INT),
    Column(
        "question_id",
        "The question's id in the study file ([[questionnaire.questions]] id).",
    ),
    Column(
        "kind",
        "text (free text), likert (a point on a labelled scale) or choice (one of the "
        "choices offered).",
    ),
    Column("question", "The question as it was shown."),
    Column(
        "answer",
        "The text typed, the choice picked, or the Likert point (1 to the number of labels).",
    ),
    Column("label", "Likert: the label of the point picked (empty for the other kinds)."),
    Column("answered_at", "When the questionnaire was submitted (UTC).", TIME),
)

BACKENDS = "mturk, prolific, mturk-replica or prolific-replica."

REVIEWS = (
    Column("participant_id", "The participant.", INT),
    _pseudonymised(
        "platform_submission_id",
        ASSIGNMENT,
        "The MTurk assignmentId or Prolific submission id reviewed "
        "(pseudonymised as in participants.csv; formerly assignment_id).",
        owner="participant_id",
    ),
    _pseudonymised(
        "platform_participant_id",
        WORKER,
        "The MTurk worker or Prolific participant (pseudonymised as in participants.csv; "
        "formerly worker_id).",
        owner="participant_id",
    ),
    Column("decision", "approved or rejected (final; sent to the review backend)."),
    Column(
        "message",
        "The review's message, sent to the participant with the decision "
        "(MTurk's RequesterFeedback, Prolific's rejection message; formerly "
        "requester_feedback).",
    ),
    Column("rejection_category", "Prolific's rejection category (empty otherwise)."),
    Column("backend", f"Where the decision was sent: {BACKENDS}"),
    Column(
        "decision_state",
        "done: the platform took the decision; pending: recorded before the platform "
        "was called and not yet confirmed (the dashboard settles it when the decision is sent "
        "again).",
        value=lambda r, ctx: r.state,
    ),
    Column("requested_at", "When the experimenter asked for the decision (UTC).", TIME),
    Column("decided_at", "When the platform took the decision (UTC; empty while pending).", TIME),
)

BONUSES = (
    Column("participant_id", "The participant.", INT),
    _pseudonymised(
        "platform_submission_id",
        ASSIGNMENT,
        "The MTurk assignmentId or Prolific submission id the bonus was paid for "
        "(pseudonymised; formerly assignment_id).",
        owner="participant_id",
    ),
    _pseudonymised(
        "platform_participant_id",
        WORKER,
        "The MTurk worker or Prolific participant paid (pseudonymised; formerly worker_id).",
        owner="participant_id",
    ),
    Column(
        "amount",
        "The bonus, in currency (two decimals).",
        NUMBER,
        lambda b, ctx: f"{b.amount_cents // 100}.{b.amount_cents % 100:02d}",
    ),
    Column("currency", "USD on MTurk; the study's currency (GBP or USD) on Prolific."),
    Column("reason", "The reason sent to the participant with the bonus."),
    Column(
        "unique_token",
        "The request's token (MTurk's UniqueRequestToken): a retry with it pays nothing more.",
    ),
    Column("backend", f"Where the bonus was sent: {BACKENDS}"),
    Column(
        "payment_state",
        "paid; or not yet confirmed: pending (recorded before the platform was "
        "called), set_up (Prolific's bonus set up, not yet paid), paying (Prolific's pay "
        "sent, its answer awaited), in_doubt (paid or not, not known yet: Prolific's pay "
        "failed after it may have paid, settled from the submission's bonus_payments, never "
        "paid twice; or an MTurk bonus unsettled for longer than MTurk remembers its request "
        "token, 24 hours: never sent again; check it on MTurk).",
        value=lambda b, ctx: b.state,
    ),
    Column(
        "setup_id",
        "Prolific's bonus set-up id (its bulk bonus payment), stored before pay was called.",
    ),
    Column("requested_at", "When the experimenter asked for the bonus (UTC).", TIME),
    Column("pay_sent_at", "When Prolific's pay was sent (UTC; empty before).", TIME),
    Column("paid_at", "When the platform took the bonus (UTC; empty until paid).", TIME),
)


MESSAGES = (
    Column(
        "message_id",
        "Message number (database id): one recipient of one message.",
        INT,
        lambda m, ctx: m.id,
    ),
    Column("participant_id", "The participant messaged.", INT),
    _pseudonymised(
        "platform_participant_id",
        WORKER,
        "The Prolific participant messaged (pseudonymised as in participants.csv; formerly "
        "worker_id).",
        owner="participant_id",
    ),
    Column("study_id", "The Prolific STUDY_ID the message was about."),
    Column("body", "The message as sent (bam-study prolific message)."),
    Column("backend", "Where it was sent: prolific or prolific-replica."),
    Column(
        "sent_with",
        "Prolific's call: messages (to one participant) or messages/bulk (the same message "
        "to several in one call).",
    ),
    Column(
        "prolific_answer",
        "Prolific's HTTP status for the call (204: sent); a message it refused is not stored.",
        INT,
        lambda m, ctx: m.answer_status,
    ),
    Column("sent_at", "When Prolific took the message (UTC).", TIME),
)


def _cell(name: str, description: str, of: str, part: int) -> Column:
    """The row (``part`` 0) or column (1) of an attention check's cell ``of``."""
    return Column(name, description, INT, lambda x, ctx: divmod(getattr(x, of), x.size)[part])


ATTENTION_CHECKS = (
    Column("participant_id", "The participant.", INT),
    Column(
        "number",
        "The check's number among the participant's, from 1.",
        INT,
        lambda x, ctx: x.number + 1,
    ),
    Column(
        "after_position",
        "The position (0-5) of the agent it followed.",
        INT,
        lambda x, ctx: ctx.position_of.get((x.participant_id, x.after_ordinal)),
    ),
    Column("size", "The grid's width and height, in cells.", INT),
    _cell("start_row", "Where the robot started: its row, from 0 at the top.", "start_cell", 0),
    _cell(
        "start_column", "Where the robot started: its column, from 0 on the left.", "start_cell", 1
    ),
    _cell("star_row", "The star's row.", "star_cell", 0),
    _cell("star_column", "The star's column.", "star_cell", 1),
    Column("moves_allowed", "The moves allowed to reach the star.", INT),
    Column("moves_made", "The moves the participant made.", INT, lambda x, ctx: len(x.moves)),
    Column(
        "moves",
        "The arrows pressed, in order, separated by spaces (UP, DOWN, LEFT, RIGHT).",
        value=lambda x, ctx: " ".join(x.moves),
    ),
    Column(
        "outcome",
        "passed (the star reached within the moves allowed), failed (the moves "
        "used up), active (being taken) or pending (not reached yet).",
        value=lambda x, ctx: x.status,
    ),
    Column("started_at", "When the check was shown (UTC; empty if not reached).", TIME),
    Column("finished_at", "When it was passed or failed (UTC).", TIME),
)

ERASED_TABLES = (
    "participants",
    "learning_sessions",
    "episodes",
    "events",
    "learner_updates",
    "status_changes",
    "questionnaire_answers",
    "attention_checks",
    "participant_tokens",
    "reviews",
    "bonuses",
    "messages",
    "mturk_replica_assignments",
    "mturk_replica_submissions",
    "mturk_replica_bonuses",
)


# The tables renamed since: their former names, for the columns named after them.
_FORMER_TABLE = {"reviews": "assignment_reviews"}


def _erased(table: str) -> Column:
    former = _FORMER_TABLE.get(table)
    return Column(
        f"{table}_rows",
        f"Rows of the {table} table erased" + (f" (formerly {former}_rows)." if former else "."),
        INT,
        lambda e, ctx: e.rows.get(table, 0),
    )


ERASURES = (
    Column("erasure_id", "Erasure number (database id).", INT, lambda e, ctx: e.id),
    Column("erased_at", "When the participant's data was erased (UTC).", TIME),
    Column(
        "erased_by",
        "participant (they withdrew from the study page) or experimenter (the "
        "dashboard or bam-study erase, on the participant's request).",
    ),
    Column(
        "participant_id",
        "The participant erased (participant_id of earlier exports; no row "
        "of any other file refers to it any more).",
        INT,
    ),
    Column("platform", "mturk, prolific or lab."),
    Column(
        "platform_participant_id",
        "The participant's platform_participant_id pseudonym, as in earlier exports (w_ + "
        "salted hash; empty for lab participants; formerly worker_id).",
        value=lambda e, ctx: e.platform_participant_pseudonym,
    ),
    Column(
        "platform_submission_id",
        "The participant's platform_submission_id pseudonym (a_ + salted hash; formerly "
        "assignment_id).",
        value=lambda e, ctx: e.platform_submission_pseudonym,
    ),
    *(_erased(table) for table in ERASED_TABLES),
)

# The quality checks are computed from the other tables (``export.quality``), not read from rows.
QUALITY = tuple(
    Column(name, description, INT if name in quality.INTEGER_COLUMNS else "text")
    for name, description in quality.COLUMNS.items()
)

# file -> its columns, in the data dictionary's order.
FILES: dict[str, tuple[Column, ...]] = {
    "participants": PARTICIPANTS,
    "sessions": SESSIONS,
    "episodes": EPISODES,
    "events": EVENTS,
    "evaluations": EVALUATIONS,
    "status_changes": STATUS_CHANGES,
    "questionnaire_answers": QUESTIONNAIRE_ANSWERS,
    "reviews": REVIEWS,
    "bonuses": BONUSES,
    "messages": MESSAGES,
    "attention_checks": ATTENTION_CHECKS,
    "erasures": ERASURES,
    "quality": QUALITY,
    "tutorial_sessions": TUTORIAL_SESSIONS,
}
# file -> column -> description: the data dictionary.
DICTIONARY: dict[str, dict[str, str]] = {
    name: {column.name: column.description for column in columns} for name, columns in FILES.items()
}
# file -> its integer columns (written as pandas' Int64: no decimal point, empty cells empty).
INTEGER_COLUMNS: dict[str, frozenset[str]] = {
    name: frozenset(column.name for column in columns if column.kind == INT)
    for name, columns in FILES.items()
}
