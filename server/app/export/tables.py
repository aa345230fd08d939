"""The study's data as tables: CSV files with a data dictionary, a zip, or pandas DataFrames.

``export_tables`` reads a study database (``storage.db.open_study_database`` opens one for
reading only) (the analysis can use it directly); ``write_export`` writes the CSVs
and ``data_dictionary.csv``. Worker and assignment ids are pseudonymised with a salted hash
(``rights.pseudonyms``: HMAC-SHA256 with ``BAM_SECRET``, or the random secret created with the
database) and completion codes left out, unless ``pseudonymize=False``.

Over 500 lines: each exported column's description (``DESCRIPTIONS``, the data dictionary) sits
in the same module as the code that fills it, so that a column is never written undescribed.
"""

from __future__ import annotations

import io
import zipfile
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import pandas as pd
from sqlalchemy import select

from server.app.export.quality import COLUMNS as QUALITY_COLUMNS
from server.app.export.quality import quality_table
from server.app.rights.pseudonyms import ASSIGNMENT, WORKER, database_secret, pseudonym
from server.app.storage.db import Database, open_study_database
from server.app.storage.figures import participant_figures, study_sessions_by_participant
from server.app.storage.models import (
    AssignmentReview,
    AttentionCheck,
    Bonus,
    Episode,
    Erasure,
    Event,
    LearnerUpdate,
    LearningSession,
    Participant,
    QuestionnaireAnswer,
    StatusChange,
)
from server.domains import make as make_environment
from server.domains.base import ACTIONS

STATUS_COLUMNS = (
    "arrived",
    "consented",
    "declined",
    "tutorial",
    "teaching",
    "questionnaire",
    "completed",
    "submitted",
    "returned",
    "abandoned",
)

# file -> column -> description: the data dictionary, and the columns in order.
DICTIONARY: dict[str, dict[str, str]] = {
    "participants": {
        "participant_id": "Participant number (database id).",
        "platform": "mturk, prolific or lab.",
        "worker_id": "MTurk workerId or Prolific PROLIFIC_PID (pseudonymised: w_ + salted hash).",
        "assignment_id": "MTurk assignmentId or Prolific SESSION_ID (pseudonymised: a_ + hash).",
        "hit_id": "MTurk hitId or Prolific STUDY_ID.",
        "status": "Latest status: arrived, consented, declined, tutorial, teaching, "
        "questionnaire (answering the post-study questionnaire), completed, submitted, returned "
        "(MTurk HIT returned, or Prolific submission RETURNED or TIMED-OUT: released) or "
        "abandoned (idle too long).",
        "prolific_status": "Prolific's latest status of the participant's submission (ACTIVE, "
        "AWAITING REVIEW, APPROVED, REJECTED, RETURNED, TIMED-OUT and the others), from its "
        "webhook or a poll; empty for other platforms or when not yet known.",
        "domain": "Domain assigned at consent (empty before).",
        "excluded": "True if the experimenter excluded the participant from analysis.",
        "exclusion_reason": "The experimenter's reason for the exclusion.",
        **{
            f"{status}_at": f"First time the participant's status became {status} (UTC, ISO 8601)."
            for status in STATUS_COLUMNS
        },
        "excluded_at": "When the participant was excluded (UTC).",
        "last_seen_at": "The participant's latest request that changed something (UTC).",
        "minutes": "Minutes from arrival to completion (or to the latest request if not completed).",
        "agents": "Study agents (learning sessions) assigned.",
        "agents_finished": "Study agents the participant finished.",
        "tutorial_step": "The tutorial step the participant reached (from 0).",
        "completion_code": "The completion code issued (left out when pseudonymised).",
    },
    "sessions": {
        "session_id": "Learning session number (database id): one agent taught by one participant.",
        "participant_id": "The participant (participants.csv).",
        "domain": "navigation, farming or gravity.",
        "environment": "The environment taught.",
        "learner": "The agent's learning algorithm (bam, model-based, global-cost, cloning).",
        "position": "Order among the participant's study agents, from 0.",
        "started_at": "When this agent's turn came (UTC).",
        "finished_at": "When the participant finished this agent (UTC; empty if not).",
        "completed": "True if the participant finished teaching this agent.",
        "opened_at": "When the participant began teaching it, past its introduction page (UTC).",
        "colour": "The agent's colour on screen.",
        "seed": "Seed of the session's learner and of its random starts and dynamics.",
        "episodes": "Episodes ended (demonstrations plus agent episodes).",
        "demonstrations": "Demonstration episodes ended.",
        "agent_episodes": "Agent episodes ended.",
        "actions": "Actions in episodes (demonstrated plus agent actions; no synthetic STAY).",
        "demonstrated_actions": "Demonstrated actions (teacher moves in demonstrate mode).",
        "agent_actions": "Actions the agent took on its own.",
        "idle_moves": "Moves in idle mode (not demonstrations; their transitions are observed).",
        "feedback_given": "Feedback signals given (+ or -).",
        "updates": "Learner updates after episodes processed (update 0, the untrained learner's evaluation, is not one; the API's `learning.updates` counts the same).",
        "final_normalized_return": "Normalised return after the session's last processed update.",
    },
    "episodes": {
        "episode_id": "Episode number (database id).",
        "session_id": "The learning session (sessions.csv, or tutorial_sessions.csv).",
        "participant_id": "The participant.",
        "session_kind": "study or tutorial.",
        "index": "Order of the episode in its session, from 0.",
        "kind": "demonstration or agent.",
        "task": "Index of the task selected during the episode.",
        "task_name": "Name of that task.",
        "start_state": "State before the episode's first action (never the task's goal in "
        "data recorded since no episode may start there; before, a demonstration's start_state "
        "was the state after its first move).",
        "end_state": "State when it ended (after the synthetic STAY, if any).",
        "started_at": "Time of the first action (UTC).",
        "ended_at": "When it ended (UTC; empty if still open).",
        "end_reason": "end (the participant), goal, horizon (agent episodes), or implicitly: "
        "task, mode, reset, finish.",
        "actions": "Actions in the episode (no synthetic STAY).",
        "update_index": "The learner update queued when it ended (evaluations.csv).",
    },
    "events": {
        "event_id": "Event number (database id; increasing in time).",
        "participant_id": "The participant.",
        "session_id": "The learning session (empty for consent, start, tutorial, submission "
        "and attention_move).",
        "seq": "The participant's sequence number of the request.",
        "kind": "consent, start, tutorial (a tutorial step reached), submission, open (teaching "
        "begun after the agent's introduction page), task, mode, move, agent_step, feedback, "
        "reset, end_episode, finish, or attention_move (a move in an attention check: state "
        "and next_state are its grid's cells, row x size + column).",
        "created_at": "When the request was committed (UTC).",
        "task": "Task selected (for task: the new one).",
        "mode": "Mode after the event: idle, demonstrate or agent.",
        "state": "The agent's state before the event.",
        "action": "The action taken (move, agent_step): STAY, UP, DOWN, LEFT or RIGHT.",
        "next_state": "The agent's state after the event (before a synthetic STAY); differs "
        "from state for a mode or task event when the agent stood on the selected task's goal "
        "with a mode on and was put at a random start.",
        "feedback": "+1 or -1 (feedback events); 0 on agent steps.",
        "episode_index": "The episode the event belongs to or ended.",
        "record": "What the learner observed: demonstration, agent_step, transition (idle move) "
        "or feedback (on the latest agent step).",
        "stay_state": "Outcome of the synthetic STAY appended to a demonstration that ended here.",
        "episode_end": "Why an episode ended at this event (see episodes.csv end_reason).",
    },
    "evaluations": {
        "session_id": "The learning session (sessions.csv).",
        "participant_id": "The participant.",
        "domain": "The session's domain.",
        "environment": "The session's environment.",
        "learner": "The session's learner.",
        "position": "The session's position.",
        "update_index": "0: the untrained learner; k >= 1: the update after the k-th episode.",
        "episodes": "Episodes ended in the session when the update was queued (cumulative).",
        "actions": "Actions in the session's episodes by then (cumulative).",
        "normalized_return": "Exact expected total return of the agent's greedy policies over all "
        "tasks divided by the optimal total return (empty if the update failed).",
        "status": "done, or failed (the update raised an error; the next one includes its data).",
        "objective": "The learner's objective after the update.",
        "update_seconds": "Time the learner update took.",
        "queued_at": "When the episode ended and the update was queued (UTC).",
        "finished_at": "When the update and its evaluation were committed (UTC).",
    },
    "status_changes": {
        "participant_id": "The participant.",
        "status": "The new status, or excluded / included (the experimenter's marks).",
        "at": "When (UTC).",
        "note": "Details (the session begun, the reason for an exclusion, ...).",
    },
    "questionnaire_answers": {
        "participant_id": "The participant.",
        "question_id": "The question's id in the study file ([[questionnaire.questions]] id).",
        "kind": "text (free text), likert (a point on a labelled scale) or choice (one of the "
        "choices offered).",
        "question": "The question as it was shown.",
        "answer": "The text typed, the choice picked, or the Likert point (1 to the number of "
        "labels).",
        "label": "Likert: the label of the point picked (empty for the other kinds).",
        "answered_at": "When the questionnaire was submitted (UTC).",
    },
    "reviews": {
        "participant_id": "The participant.",
        "assignment_id": "The MTurk assignmentId or Prolific submission id reviewed "
        "(pseudonymised as in participants.csv).",
        "worker_id": "The MTurk worker or Prolific participant (pseudonymised as in "
        "participants.csv).",
        "decision": "approved or rejected (final; sent to the review backend).",
        "requester_feedback": "The review's message, sent to the participant with the decision "
        "(MTurk's RequesterFeedback, Prolific's rejection message; the column keeps its "
        "published name, the API and the database call it message).",
        "rejection_category": "Prolific's rejection category (empty otherwise).",
        "backend": "Where the decision was sent: mturk, prolific, mturk-replica or "
        "prolific-replica.",
        "decision_state": "done: the platform took the decision; pending: recorded before the platform "
        "was called and not yet confirmed (the dashboard settles it when the decision is sent "
        "again).",
        "requested_at": "When the experimenter asked for the decision (UTC).",
        "decided_at": "When the platform took the decision (UTC; empty while pending).",
    },
    "bonuses": {
        "participant_id": "The participant.",
        "assignment_id": "The MTurk assignmentId or Prolific submission id the bonus was paid "
        "for (pseudonymised).",
        "worker_id": "The MTurk worker or Prolific participant paid (pseudonymised).",
        "amount": "The bonus, in currency (two decimals).",
        "currency": "USD on MTurk; the study's currency (GBP or USD) on Prolific.",
        "reason": "The reason sent to the participant with the bonus.",
        "unique_token": "The request's token (MTurk's UniqueRequestToken): a retry with it pays "
        "nothing more.",
        "backend": "Where the bonus was sent: mturk, prolific, mturk-replica or prolific-replica.",
        "payment_state": "paid; or not yet confirmed: pending (recorded before the platform was "
        "called), set_up (Prolific's bonus set up, not yet paid), paying (Prolific's pay "
        "called, outcome not known).",
        "setup_id": "Prolific's bonus set-up id (its bulk bonus payment), stored before pay "
        "was called.",
        "requested_at": "When the experimenter asked for the bonus (UTC).",
        "paid_at": "When the platform took the bonus (UTC; empty until paid).",
    },
    "attention_checks": {
        "participant_id": "The participant.",
        "number": "The check's number among the participant's, from 1.",
        "after_position": "The position (0-5) of the agent it followed.",
        "size": "The grid's width and height, in cells.",
        "start_row": "Where the robot started: its row, from 0 at the top.",
        "start_column": "Where the robot started: its column, from 0 on the left.",
        "star_row": "The star's row.",
        "star_column": "The star's column.",
        "moves_allowed": "The moves allowed to reach the star.",
        "moves_made": "The moves the participant made.",
        "moves": "The arrows pressed, in order, separated by spaces (UP, DOWN, LEFT, RIGHT).",
        "outcome": "passed (the star reached within the moves allowed), failed (the moves "
        "used up), active (being taken) or pending (not reached yet).",
        "started_at": "When the check was shown (UTC; empty if not reached).",
        "finished_at": "When it was passed or failed (UTC).",
    },
    "erasures": {
        "erasure_id": "Erasure number (database id).",
        "erased_at": "When the participant's data was erased (UTC).",
        "erased_by": "participant (they withdrew from the study page) or experimenter (the "
        "dashboard or bam-study erase, on the participant's request).",
        "participant_id": "The participant erased (participant_id of earlier exports; no row "
        "of any other file refers to it any more).",
        "platform": "mturk, prolific or lab.",
        "worker_id": "The participant's worker pseudonym, as in earlier exports (w_ + salted "
        "hash; empty for lab participants).",
        "assignment_id": "The participant's assignment pseudonym (a_ + salted hash).",
        **{
            f"{table}_rows": f"Rows of the {table} table erased."
            for table in (
                "participants",
                "learning_sessions",
                "episodes",
                "events",
                "learner_updates",
                "status_changes",
                "questionnaire_answers",
                "attention_checks",
                "participant_tokens",
                "assignment_reviews",
                "bonuses",
                "mturk_replica_assignments",
                "mturk_replica_submissions",
                "mturk_replica_bonuses",
            )
        },
    },
    "quality": QUALITY_COLUMNS,
}
# Integer columns, some of them with empty cells (written without a decimal point).
INTEGER_COLUMNS = frozenset(
    {
        "participant_id",
        "session_id",
        "episode_id",
        "event_id",
        "position",
        "seed",
        "seq",
        "task",
        "state",
        "next_state",
        "feedback",
        "episode_index",
        "stay_state",
        "index",
        "start_state",
        "end_state",
        "update_index",
        "episodes",
        "actions",
        "agents",
        "agents_finished",
        "tutorial_step",
        "demonstrations",
        "agent_episodes",
        "demonstrated_actions",
        "agent_actions",
        "idle_moves",
        "feedback_given",
        "updates",
        "erasure_id",
        "number",
        "after_position",
        "size",
        "start_row",
        "start_column",
        "star_row",
        "star_column",
        "moves_allowed",
        "moves_made",
        "attention_checks",
        "failed_attention_checks",
        *(name for name in DICTIONARY["erasures"] if name.endswith("_rows")),
    }
)
DICTIONARY["tutorial_sessions"] = {
    key: value for key, value in DICTIONARY["sessions"].items() if key != "position"
}
DESCRIPTIONS = {
    "participants": "One row per participant (an arrival that was not a preview).",
    "sessions": "One row per learning session of the study (the tutorial's are apart).",
    "tutorial_sessions": "One row per tutorial learning session (not analysed).",
    "episodes": "One row per episode of every learning session, tutorials included.",
    "events": "One row per acknowledged participant request, in order (append-only log).",
    "evaluations": "One row per processed learner update of the study's sessions.",
    "status_changes": "One row per change of a participant's status.",
    "questionnaire_answers": "One row per question answered in the post-study questionnaire "
    "(an optional question left unanswered has none; a study without a questionnaire, none).",
    "reviews": "One row per submitted MTurk assignment or Prolific submission the "
    "experimenter approved or rejected.",
    "bonuses": "One row per bonus the experimenter paid (or asked the platform to pay).",
    "attention_checks": "One row per instructional attention check of a participant (the "
    "study file's [attention_checks]; none without it): move the robot to the star.",
    "quality": "One row per participant who completed: quality checks built for teaching "
    "(completion time against the others', idle stretches, optimal demonstrations, consistent "
    "feedback, attention checks failed) and the rejection ground, if any, that Prolific accepts for them. None rejects "
    "anybody by itself.",
    "erasures": "One row per participant whose data was erased (withdrawal or request): the "
    "other files hold nothing of theirs; remove their rows (by participant_id or pseudonym) "
    "from copies exported before.",
    "data_dictionary": "Every file's columns. In every file, each line of a text cell that "
    "begins with =, +, -, @, a tab or a carriage return is written with an apostrophe (') "
    "before it, so that a spreadsheet shows it as text instead of running it as a formula; "
    "remove the apostrophe that begins each such line to get the text as stored. A text cell "
    "that holds a line break (any of Unicode's) is in double quotes. Numbers are written as "
    "they are.",
}
FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r")
# What str.splitlines splits on; "\n" ends the rows.
OTHER_LINE_BREAKS = "\r\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029"


def _iso(value: Any) -> Any:
    return value.isoformat() if value is not None and hasattr(value, "isoformat") else value


def _frame(name: str, rows: Iterable[dict[str, Any]]) -> pd.DataFrame:
    return pd.DataFrame(list(rows), columns=list(DICTIONARY[name]))


def export_tables(
    db: Database | str, pseudonymize: bool = True, secret: str | None = None
) -> dict[str, pd.DataFrame]:
    """Every export table as a DataFrame (columns as in ``DICTIONARY``; times as ISO strings),
    from a study database or its URL."""
    if isinstance(db, str):
        database = open_study_database(db)
        try:
            return export_tables(database, pseudonymize, secret)
        finally:
            database.dispose()
    if pseudonymize and secret is None:
        secret = database_secret(db)
    with db.read() as s:
        participants = s.scalars(select(Participant).order_by(Participant.id)).all()
        changes = s.scalars(select(StatusChange).order_by(StatusChange.id)).all()
        answers = s.scalars(select(QuestionnaireAnswer).order_by(QuestionnaireAnswer.id)).all()
        reviews = s.scalars(select(AssignmentReview).order_by(AssignmentReview.id)).all()
        bonuses = s.scalars(select(Bonus).order_by(Bonus.id)).all()
        erasures = s.scalars(select(Erasure).order_by(Erasure.id)).all()
        checks = s.scalars(
            select(AttentionCheck).order_by(AttentionCheck.participant_id, AttentionCheck.number)
        ).all()
        sessions = s.scalars(select(LearningSession).order_by(LearningSession.id)).all()
        episodes = s.scalars(select(Episode).order_by(Episode.id)).all()
        updates = s.execute(
            select(
                LearnerUpdate.session_id,
                LearnerUpdate.update_index,
                LearnerUpdate.status,
                LearnerUpdate.episodes,
                LearnerUpdate.actions,
                LearnerUpdate.normalized_return,
                LearnerUpdate.objective,
                LearnerUpdate.seconds,
                LearnerUpdate.queued_at,
                LearnerUpdate.finished_at,
            )
            .where(LearnerUpdate.status != "pending")
            .order_by(LearnerUpdate.session_id, LearnerUpdate.update_index)
        ).all()
        events = s.execute(
            select(
                Event.id,
                Event.participant_id,
                Event.session_id,
                Event.seq,
                Event.kind,
                Event.created_at,
                Event.task,
                Event.mode,
                Event.state,
                Event.action,
                Event.next_state,
                Event.feedback,
                Event.episode_index,
                Event.record,
                Event.stay_state,
                Event.episode_end,
            ).order_by(Event.id)
        ).all()

    first_at: dict[int, dict[str, Any]] = {}
    for change in changes:
        first_at.setdefault(change.participant_id, {}).setdefault(change.status, change.at)
    session_by_id = {x.id: x for x in sessions}
    scrubbed_ids = {p.id for p in participants if p.identifiers_scrubbed_at is not None}

    def scrubbed(participant_id: int) -> bool:
        return participant_id in scrubbed_ids

    counts: dict[int, dict[str, int]] = {}
    for event in events:
        if event.session_id is None:
            continue
        c = counts.setdefault(event.session_id, {"demo": 0, "agent": 0, "feedback": 0})
        if event.record == "demonstration":
            c["demo"] += 1
        elif event.record == "agent_step":
            c["agent"] += 1
        elif event.record == "feedback":
            c["feedback"] += 1
    episode_kinds: dict[int, dict[str, int]] = {}
    for episode in episodes:
        if episode.ended_at is not None:
            k = episode_kinds.setdefault(episode.session_id, {"demonstration": 0, "agent": 0})
            k[episode.kind] += 1
    last_return: dict[int, float | None] = {}
    processed: dict[int, int] = {}
    for update in updates:
        last_return[update.session_id] = update.normalized_return
        if update.update_index > 0:
            processed[update.session_id] = processed.get(update.session_id, 0) + 1

    def platform_ids(
        worker_id: str | None, assignment_id: str | None, scrubbed: bool = False
    ) -> dict[str, str | None]:
        if not pseudonymize or scrubbed:  # a scrubbed participant's ids are pseudonyms already
            return {"worker_id": worker_id, "assignment_id": assignment_id}
        assert secret is not None
        return {
            "worker_id": pseudonym(secret, worker_id, WORKER),
            "assignment_id": pseudonym(secret, assignment_id, ASSIGNMENT),
        }

    study_sessions = study_sessions_by_participant(sessions)

    def participant_row(p: Participant) -> dict[str, Any]:
        at = first_at.get(p.id, {})
        figures = participant_figures(p, study_sessions.get(p.id, []), at.get("completed"))
        row = {
            "participant_id": p.id,
            "platform": p.platform,
            "worker_id": p.worker_id,
            "assignment_id": p.assignment_id,
            "hit_id": p.hit_id,
            "status": p.status,
            "prolific_status": p.prolific_status,
            "domain": p.domain,
            "excluded": p.excluded_at is not None,
            "exclusion_reason": p.exclusion_reason,
            **{f"{status}_at": _iso(at.get(status)) for status in STATUS_COLUMNS},
            "excluded_at": _iso(p.excluded_at),
            "last_seen_at": _iso(p.last_seen_at),
            "minutes": figures.minutes,
            "agents": figures.agents,
            "agents_finished": figures.agents_finished,
            "tutorial_step": p.tutorial_step,
            "completion_code": p.completion_code,
        }
        if pseudonymize:
            row.update(platform_ids(p.worker_id, p.assignment_id, scrubbed(p.id)))
            row["completion_code"] = None
        return row

    def erasure_row(e: Erasure) -> dict[str, Any]:
        return {
            "erasure_id": e.id,
            "erased_at": _iso(e.erased_at),
            "erased_by": e.erased_by,
            "participant_id": e.participant_id,
            "platform": e.platform,
            "worker_id": e.worker_pseudonym,
            "assignment_id": e.assignment_pseudonym,
            **{
                name: e.rows.get(name.removesuffix("_rows"), 0)
                for name in DICTIONARY["erasures"]
                if name.endswith("_rows")
            },
        }

    def review_row(r: AssignmentReview) -> dict[str, Any]:
        return {
            "participant_id": r.participant_id,
            **platform_ids(r.worker_id, r.assignment_id, scrubbed(r.participant_id)),
            "decision": r.decision,
            "requester_feedback": r.message,
            "rejection_category": r.rejection_category,
            "backend": r.backend,
            "decision_state": r.state,
            "requested_at": _iso(r.requested_at),
            "decided_at": _iso(r.decided_at),
        }

    def bonus_row(b: Bonus) -> dict[str, Any]:
        return {
            "participant_id": b.participant_id,
            **platform_ids(b.worker_id, b.assignment_id, scrubbed(b.participant_id)),
            "amount": f"{b.amount_cents // 100}.{b.amount_cents % 100:02d}",
            "currency": b.currency,
            "reason": b.reason,
            "unique_token": b.unique_token,
            "backend": b.backend,
            "payment_state": b.state,
            "setup_id": b.setup_id,
            "requested_at": _iso(b.requested_at),
            "paid_at": _iso(b.paid_at),
        }

    def answer_row(a: QuestionnaireAnswer) -> dict[str, Any]:
        return {
            "participant_id": a.participant_id,
            "question_id": a.question_id,
            "kind": a.kind,
            "question": a.question,
            "answer": a.answer,
            "label": a.label,
            "answered_at": _iso(a.answered_at),
        }

    def session_row(x: LearningSession) -> dict[str, Any]:
        c = counts.get(x.id, {"demo": 0, "agent": 0, "feedback": 0})
        k = episode_kinds.get(x.id, {"demonstration": 0, "agent": 0})
        return {
            "session_id": x.id,
            "participant_id": x.participant_id,
            "domain": x.domain,
            "environment": x.environment,
            "learner": x.learner,
            "position": x.position,
            "started_at": _iso(x.started_at),
            "finished_at": _iso(x.finished_at),
            "completed": bool(x.completed),
            "opened_at": _iso(x.opened_at),
            "colour": x.colour_name,
            "seed": x.seed,
            "episodes": x.episodes,
            "demonstrations": k["demonstration"],
            "agent_episodes": k["agent"],
            "actions": x.actions,
            "demonstrated_actions": c["demo"],
            "agent_actions": c["agent"],
            "idle_moves": x.idle_moves,
            "feedback_given": c["feedback"],
            "updates": processed.get(x.id, 0),
            "final_normalized_return": last_return.get(x.id),
        }

    def episode_row(e: Episode) -> dict[str, Any]:
        session = session_by_id[e.session_id]
        env = make_environment(session.environment)
        return {
            "episode_id": e.id,
            "session_id": e.session_id,
            "participant_id": session.participant_id,
            "session_kind": session.kind,
            "index": e.index,
            "kind": e.kind,
            "task": e.task,
            "task_name": env.tasks[e.task].name,
            "start_state": e.start_state,
            "end_state": e.end_state,
            "started_at": _iso(e.started_at),
            "ended_at": _iso(e.ended_at),
            "end_reason": e.end_reason,
            "actions": e.actions,
            "update_index": e.update_index,
        }

    def event_row(e: Any) -> dict[str, Any]:
        return {
            "event_id": e.id,
            "participant_id": e.participant_id,
            "session_id": e.session_id,
            "seq": e.seq,
            "kind": e.kind,
            "created_at": _iso(e.created_at),
            "task": e.task,
            "mode": e.mode,
            "state": e.state,
            "action": ACTIONS[e.action] if e.action is not None else None,
            "next_state": e.next_state,
            "feedback": e.feedback,
            "episode_index": e.episode_index,
            "record": e.record,
            "stay_state": e.stay_state,
            "episode_end": e.episode_end,
        }

    def check_row(x: AttentionCheck) -> dict[str, Any]:
        start, star = divmod(x.start_cell, x.size), divmod(x.star_cell, x.size)
        return {
            "participant_id": x.participant_id,
            "number": x.number + 1,
            "after_position": position_of.get((x.participant_id, x.after_ordinal)),
            "size": x.size,
            "start_row": start[0],
            "start_column": start[1],
            "star_row": star[0],
            "star_column": star[1],
            "moves_allowed": x.moves_allowed,
            "moves_made": len(x.moves),
            "moves": " ".join(x.moves),
            "outcome": x.status,
            "started_at": _iso(x.started_at),
            "finished_at": _iso(x.finished_at),
        }

    position_of = {(x.participant_id, x.ordinal): x.position for x in sessions}

    def evaluation_rows() -> Iterable[dict[str, Any]]:
        for u in updates:
            session = session_by_id[u.session_id]
            if session.kind != "study":
                continue
            yield {
                "session_id": u.session_id,
                "participant_id": session.participant_id,
                "domain": session.domain,
                "environment": session.environment,
                "learner": session.learner,
                "position": session.position,
                "update_index": u.update_index,
                "episodes": u.episodes,
                "actions": u.actions,
                "normalized_return": u.normalized_return,
                "status": u.status,
                "objective": u.objective,
                "update_seconds": u.seconds,
                "queued_at": _iso(u.queued_at),
                "finished_at": _iso(u.finished_at),
            }

    tutorial_columns = DICTIONARY["tutorial_sessions"]
    tables = {
        "participants": _frame("participants", map(participant_row, participants)),
        "sessions": _frame("sessions", (session_row(x) for x in sessions if x.kind == "study")),
        "tutorial_sessions": _frame(
            "tutorial_sessions",
            (
                {k: v for k, v in session_row(x).items() if k in tutorial_columns}
                for x in sessions
                if x.kind == "tutorial"
            ),
        ),
        "episodes": _frame("episodes", map(episode_row, episodes)),
        "events": _frame("events", map(event_row, events)),
        "evaluations": _frame("evaluations", evaluation_rows()),
        "status_changes": _frame(
            "status_changes",
            (
                {
                    "participant_id": c.participant_id,
                    "status": c.status,
                    "at": _iso(c.at),
                    "note": c.note,
                }
                for c in changes
            ),
        ),
        "questionnaire_answers": _frame("questionnaire_answers", map(answer_row, answers)),
        "reviews": _frame("reviews", map(review_row, reviews)),
        "bonuses": _frame("bonuses", map(bonus_row, bonuses)),
        "attention_checks": _frame("attention_checks", map(check_row, checks)),
        "erasures": _frame("erasures", map(erasure_row, erasures)),
    }
    for frame in tables.values():
        for column in frame.columns:
            if column in INTEGER_COLUMNS:
                frame[column] = frame[column].astype("Int64")
    tables["quality"] = quality_table(tables)
    return tables


def dictionary_frame() -> pd.DataFrame:
    rows = [
        {"file": f"{name}.csv", "column": column, "description": description}
        for name, columns in DICTIONARY.items()
        for column, description in columns.items()
    ]
    rows += [
        {"file": f"{name}.csv", "column": "", "description": text}
        for name, text in DESCRIPTIONS.items()
    ]
    return pd.DataFrame(rows, columns=["file", "column", "description"])


def as_text(value: Any) -> Any:
    """A text cell no line of which a spreadsheet will run as a formula (``DESCRIPTIONS``)."""
    if not isinstance(value, str):
        return value
    lines = value.splitlines(keepends=True)
    if not any(line.startswith(FORMULA_STARTS) for line in lines):
        return value
    return "".join("'" + line if line.startswith(FORMULA_STARTS) else line for line in lines)


def neutralised(frame: pd.DataFrame) -> pd.DataFrame:
    text = [name for name in frame.columns if pd.api.types.is_string_dtype(frame[name].dtype)]
    if not text:
        return frame
    frame = frame.copy()
    for name in text:
        frame[name] = frame[name].map(as_text)
    return frame


def csv_text(frame: pd.DataFrame) -> str:
    """``frame`` as CSV, its text cells guarded (``as_text``) and every cell holding a line
    break in quotes, so that no reader splits its row. The csv module quotes a cell holding a
    character of the line terminator only: the rows are written ended by every line break, and
    each such ending outside quotes then becomes "\\n"."""
    row_end = "\n" + OTHER_LINE_BREAKS
    pieces = neutralised(frame).to_csv(index=False, lineterminator=row_end).split(row_end)
    text, quoted = [], False
    for piece in pieces[:-1]:
        quoted ^= piece.count('"') % 2 == 1  # a quote inside quotes is doubled
        text += [piece, row_end if quoted else "\n"]
    text.append(pieces[-1])
    return "".join(text)


def export_files(tables: dict[str, pd.DataFrame]) -> dict[str, bytes]:
    files = {f"{name}.csv": csv_text(frame).encode() for name, frame in tables.items()}
    files["data_dictionary.csv"] = csv_text(dictionary_frame()).encode()
    return files


def write_export(tables: dict[str, pd.DataFrame], out: Path) -> list[Path]:
    """Write the CSVs and the data dictionary into ``out``; returns the files written."""
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, content in export_files(tables).items():
        path = out / name
        path.write_bytes(content)
        written.append(path)
    return written


def export_zip(tables: dict[str, pd.DataFrame]) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, content in export_files(tables).items():
            archive.writestr(name, content)
    return buffer.getvalue()
