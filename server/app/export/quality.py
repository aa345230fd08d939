"""Quality checks built for teaching, one row per participant (``quality.csv``): how long they
took against the other participants, their longest idle stretch, how many of their
demonstrated moves were optimal, how often their + and - agreed with whether the agent's
move was better or worse than average and whether the paper's model of feedback explains them
better than random presses do, and how many instructional attention checks they failed. None
rejects anybody by itself: each row says which ground a platform accepts for a rejection, if
any (Prolific: ``FAILED_CHECK`` for failed instructional attention checks, more
than one in a study of five minutes or more; ``TOO_QUICKLY`` only for exceptionally fast
completion, three standard deviations below the mean; never for poor performance).

Computed from the export's tables (``participants``, ``events``, ``attention_checks``), so that
it reads a database or an export alike.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
import pandas as pd

from server.app.storage.vocabulary import CheckStatus, Observed
from server.domains import make as make_environment
from server.domains.base import ACTIONS
from server.teacher import TIE_TOLERANCE, Teacher


@dataclass(frozen=True)
class Thresholds:
    """Where each check flags a participant."""

    fast_sd: float = 3.0  # completion this many s.d. below the others' mean
    idle_minutes: float = 5.0  # a gap this long between two requests
    demonstration_share: float = 0.7  # optimal demonstrated moves below this share
    # Flag the + and - whose log likelihood ratio, the paper's model of feedback against random
    # presses, is at most this (0: random presses explain them at least as well).
    feedback_log_ratio: float = 0.0
    least_moves: int = 10  # fewer demonstrated moves (feedback signals): not judged
    # Prolific: a study of five minutes or more needs more than one failed attention check.
    long_study_minutes: float = 5.0
    # The study's length; None: the median minutes of the participants who completed.
    study_minutes: float | None = None

    def failures_needed(self, study_minutes: float) -> int:
        """Failed attention checks that support Prolific's FAILED_CHECK."""
        return 2 if study_minutes >= self.long_study_minutes else 1


# The checks that flag a participant (each a column of its own, and a word of ``flags``).
FLAGS = (
    "exceptionally_fast",
    "long_idle",
    "poor_demonstrations",
    "inconsistent_feedback",
    "failed_attention",
)

COLUMNS: dict[str, str] = {
    "participant_id": "The participant (participants.csv).",
    "minutes": "Minutes from arrival to completion.",
    "minutes_z": "How many standard deviations the participant's minutes are from the mean of "
    "the other participants who completed (empty with fewer than three others).",
    "exceptionally_fast": "True when minutes_z is 3 or more standard deviations below the "
    "mean (Prolific's 'exceptionally fast').",
    "longest_idle_minutes": "The longest time between two of the participant's requests.",
    "long_idle": "True when longest_idle_minutes is 5 minutes or more.",
    "demonstrated_moves": "Moves the participant demonstrated (study agents).",
    "optimal_demonstration_share": "Share of the demonstrated moves that are optimal for the "
    "selected task under the true dynamics (key-mashing scores near chance; empty with fewer "
    "than 10 moves).",
    "poor_demonstrations": "True when optimal_demonstration_share is below 0.7.",
    "feedback_signals": "Feedback signals (+ or -) given on the agent's moves (study agents).",
    "consistent_feedback_share": "Share of the + and - that agree with whether the agent's "
    "move was better or worse than the average move there for the selected task under the "
    "true dynamics (+ for better, - for worse; signals on a move where every move is as good "
    "are not counted; empty with fewer than 10).",
    "feedback_log_likelihood_ratio": "How much better the paper's model of feedback (A-SABL, "
    "epsilon 0.05 and alpha 1, on the true dynamics' Q) explains the participant's + and - than "
    "random presses do: the sum over the signals counted in consistent_feedback_share of "
    "log(p / 0.5), p the model's probability of that sign on that move; above 0 the model "
    "explains them better (empty with fewer than 10 signals).",
    "inconsistent_feedback": "True when feedback_log_likelihood_ratio is 0 or below: random + "
    "and - explain the participant's at least as well as the paper's model of a teacher does.",
    "attention_checks": "Instructional attention checks the participant took (passed or "
    "failed; attention_checks.csv).",
    "failed_attention_checks": "Attention checks failed (the moves allowed used up before the "
    "robot reached the star).",
    "failed_attention": "True when failed_attention_checks is at least two, or at least one in "
    "a study under five minutes (the study's length: the median minutes of the participants "
    "who completed), as Prolific requires for rejecting on failed attention checks.",
    "flags": "The checks flagged, separated by spaces (empty: none).",
    "prolific_ground": "The Prolific rejection ground the flags support: FAILED_CHECK "
    "(failed_attention), else TOO_QUICKLY (exceptionally fast), else none. Idle stretches and "
    "poor demonstrations or feedback are not grounds: Prolific does not allow rejecting for "
    "performance.",
}
# Written as pandas' Int64 (no decimal point).
INTEGER_COLUMNS = (
    "participant_id",
    "demonstrated_moves",
    "feedback_signals",
    "attention_checks",
    "failed_attention_checks",
)


@cache
def _teacher(environment: str) -> Teacher:
    return Teacher(make_environment(environment))


def _optimal(environment: str, task: int, state: int, action: int) -> bool:
    return bool(action in _teacher(environment).best_actions(task, state))


def _advantage(environment: str, task: int, state: int, action: int) -> float:
    """How much better the action is than the average action there (true dynamics)."""
    row = _teacher(environment).q_values(task)[state]
    return float(row[action] - row.mean())


def _sign_log_ratio(environment: str, advantage: float, feedback: int) -> float:
    """log(p / 0.5), p the probability that a teacher of the paper's model (the simulated
    teacher's A-SABL) gives this sign, given that they give one, on a move of this advantage."""
    positive, negative = _teacher(environment).feedback_model.probabilities(np.array([advantage]))
    given = positive[0] if feedback > 0 else negative[0]
    return float(np.log(2 * given / (positive[0] + negative[0])))


def _share(hits: list[bool], least: int) -> float | None:
    return round(sum(hits) / len(hits), 4) if len(hits) >= least else None


def quality_table(
    tables: dict[str, pd.DataFrame], thresholds: Thresholds = Thresholds()
) -> pd.DataFrame:
    """One row per participant who completed (``COLUMNS``)."""
    participants = tables["participants"]
    done = participants[participants["completed_at"].notna()]
    sessions = tables["sessions"].set_index("session_id")["environment"].to_dict()
    events = tables["events"]
    events = events[events["session_id"].isin(list(sessions))]
    minutes = done.set_index("participant_id")["minutes"].astype(float)
    study_minutes = thresholds.study_minutes
    if study_minutes is None:
        study_minutes = float(minutes.median()) if len(minutes) else 0.0
    checks = tables.get("attention_checks")  # an export made before the checks has none
    if checks is None:
        checks = pd.DataFrame(columns=["participant_id", "outcome"])
    taken = checks[checks["outcome"].isin([CheckStatus.PASSED, CheckStatus.FAILED])]
    checks_taken = taken.groupby("participant_id").size().to_dict()
    checks_failed = (
        taken[taken["outcome"] == CheckStatus.FAILED].groupby("participant_id").size().to_dict()
    )
    seen = tables["events"].assign(at=pd.to_datetime(tables["events"]["created_at"]))
    rows: list[dict[str, Any]] = []
    for participant_id, own_minutes in minutes.items():
        others = minutes.drop(participant_id)
        z = None
        if len(others) >= 3 and others.std(ddof=1) > 0:
            z = round(float((own_minutes - others.mean()) / others.std(ddof=1)), 2)
        times = seen.loc[seen["participant_id"] == participant_id, "at"].sort_values()
        idle = float(times.diff().max().total_seconds() / 60) if len(times) > 1 else 0.0
        demonstrated: list[bool] = []
        consistent: list[bool] = []
        log_ratio = 0.0
        mine = events[events["participant_id"] == participant_id].sort_values("event_id")
        latest_agent: dict[int, tuple[int, int, int]] = {}
        for event in mine.itertuples(index=False):
            environment = sessions[event.session_id]
            if event.record == Observed.DEMONSTRATION:
                action = ACTIONS.index(event.action)
                demonstrated.append(_optimal(environment, event.task, event.state, action))
            elif event.record == Observed.AGENT_STEP:
                latest_agent[event.session_id] = (
                    int(event.task),
                    int(event.state),
                    ACTIONS.index(event.action),
                )
            elif event.record == Observed.FEEDBACK and event.session_id in latest_agent:
                task, state, action = latest_agent[event.session_id]
                advantage = _advantage(environment, task, state, action)
                if abs(advantage) > TIE_TOLERANCE:  # every move as good: no right answer
                    consistent.append((advantage > 0) == (int(event.feedback) > 0))
                    log_ratio += _sign_log_ratio(environment, advantage, int(event.feedback))
        demo_share = _share(demonstrated, thresholds.least_moves)
        feedback_share = _share(consistent, thresholds.least_moves)
        feedback_ratio = round(log_ratio, 3) if feedback_share is not None else None
        row: dict[str, Any] = {
            "participant_id": participant_id,
            "minutes": own_minutes,
            "minutes_z": z,
            "exceptionally_fast": z is not None and z <= -thresholds.fast_sd,
            "longest_idle_minutes": round(idle, 2),
            "long_idle": idle >= thresholds.idle_minutes,
            "demonstrated_moves": len(demonstrated),
            "optimal_demonstration_share": demo_share,
            "poor_demonstrations": demo_share is not None
            and demo_share < thresholds.demonstration_share,
            "feedback_signals": len(consistent),
            "consistent_feedback_share": feedback_share,
            "feedback_log_likelihood_ratio": feedback_ratio,
            "inconsistent_feedback": feedback_ratio is not None
            and feedback_ratio <= thresholds.feedback_log_ratio,
            "attention_checks": int(checks_taken.get(participant_id, 0)),
            "failed_attention_checks": int(checks_failed.get(participant_id, 0)),
        }
        row["failed_attention"] = row["failed_attention_checks"] >= thresholds.failures_needed(
            study_minutes
        )
        flags = [name for name in FLAGS if row[name]]
        row["flags"] = " ".join(flags)
        row["prolific_ground"] = (
            "FAILED_CHECK"
            if row["failed_attention"]
            else "TOO_QUICKLY"
            if row["exceptionally_fast"]
            else "none"
        )
        rows.append(row)
    frame = pd.DataFrame(rows, columns=list(COLUMNS))
    for name in INTEGER_COLUMNS:
        frame[name] = frame[name].astype("Int64")
    return frame
