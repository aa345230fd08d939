"""The export's files and the columns the analysis reads from them (``bam-study export``
writes them; ``server.app.export.columns.DICTIONARY`` describes every column)."""

from __future__ import annotations

SESSIONS_FILE = "sessions.csv"
EVALUATIONS_FILE = "evaluations.csv"
PARTICIPANTS_FILE = "participants.csv"
EPISODES_FILE = "episodes.csv"
QUALITY_FILE = "quality.csv"
REVIEWS_FILE = "reviews.csv"
ERASURES_FILE = "erasures.csv"
EPISODE_COLUMNS = (
    "session_id",
    "kind",
    "start_state",
    "end_state",
    "end_reason",
    "actions",
    "update_index",
)

SESSION_COLUMNS = (
    "session_id",
    "participant_id",
    "domain",
    "environment",
    "learner",
    "position",
    "started_at",
    "finished_at",
    "completed",
)
EVALUATION_COLUMNS = (
    "session_id",
    "participant_id",
    "domain",
    "environment",
    "learner",
    "position",
    "update_index",
    "episodes",
    "actions",
    "normalized_return",
)
# Columns of an evaluation that must agree with its learning session.
SHARED_COLUMNS = ("participant_id", "domain", "environment", "learner", "position")
