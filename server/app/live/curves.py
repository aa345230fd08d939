"""Learning as it happens: per environment and learner, the mean normalised return against
episodes so far, with its standard error, over the study's learning sessions, and the share of
sessions past each threshold: the computation of the analysis's learning-curve figure
(``analysis/plots.py`` imports ``step_values`` and ``mean_and_standard_error`` from here), on
the evaluations in the database now.

Each session's curve is a step function: at a count x it is the normalised return of the
session's latest evaluation made at a count of at most x (its last evaluation carries forward;
before its first it has no value and does not count). The curves are evaluated on the union of
the counts at which any session of the environment was evaluated, so the means are exact.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from sqlalchemy import Connection, select

from server.app.storage.tables import PARTICIPANTS, SESSIONS, UPDATES
from server.app.storage.vocabulary import SessionKind, UpdateStatus

# The analysis's default thresholds (``analysis.options.DEFAULT_THRESHOLDS``; a test holds them
# equal): the fractions of the best return a session may reach.
THRESHOLDS = (0.5, 0.8)


def step_values(counts: np.ndarray, returns: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """One session's normalised return at each grid count (NaN before its first evaluation).

    ``counts`` are the session's cumulative counts in update order (non-decreasing); where
    several updates share a count, the latest one holds."""
    index = np.searchsorted(counts, grid, side="right") - 1
    values = np.full(len(grid), np.nan)
    valid = index >= 0
    values[valid] = returns[index[valid]]
    return values


def mean_and_standard_error(values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per column of a sessions x grid array with NaN for "no value": the mean, the standard
    error of the mean (NaN with fewer than two values) and the number of values."""
    present = ~np.isnan(values)
    n = present.sum(axis=0)
    filled = np.where(present, values, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(n > 0, filled.sum(axis=0) / n, np.nan)
        squares = np.where(present, (values - mean) ** 2, 0.0).sum(axis=0)
        se = np.where(n > 1, np.sqrt(squares / (n - 1)) / np.sqrt(n), np.nan)
    return mean, se, n


def _number(value: float) -> float | None:
    return None if np.isnan(value) else round(float(value), 4)


def live_curves(c: Connection, thresholds: tuple[float, ...] = THRESHOLDS) -> dict[str, Any]:
    """Per environment, per learner: ``episodes`` (the grid), ``mean``, ``se`` and ``n`` at each,
    ``sessions`` and ``past`` (the share of sessions with an evaluation at or above each
    threshold); over the study sessions (not the tutorial's) of participants not excluded, in
    progress or finished."""
    s, u = SESSIONS.c, UPDATES.c
    rows = c.execute(
        select(s.environment, s.learner, u.session_id, u.episodes, u.normalized_return)
        .join(SESSIONS, s.id == u.session_id)
        .join(PARTICIPANTS, PARTICIPANTS.c.id == s.participant_id)
        .where(
            s.kind == SessionKind.STUDY,
            PARTICIPANTS.c.excluded_at.is_(None),
            u.status == UpdateStatus.DONE,
            u.normalized_return.is_not(None),
        )
        .order_by(s.environment, s.learner, u.session_id, u.update_index)
    ).all()
    by_environment: dict[str, dict[str, dict[int, list[tuple[int, float]]]]] = {}
    for row in rows:
        sessions = by_environment.setdefault(row.environment, {}).setdefault(row.learner, {})
        sessions.setdefault(row.session_id, []).append((row.episodes, row.normalized_return))
    environments = []
    for environment, learners in by_environment.items():
        counts = [e for sessions in learners.values() for pts in sessions.values() for e, _ in pts]
        grid = np.unique(np.concatenate([[0], np.asarray(counts, dtype=float)]))
        curves = []
        for learner, sessions in sorted(learners.items()):
            values = np.vstack(
                [
                    step_values(
                        np.asarray([e for e, _ in points], dtype=float),
                        np.asarray([r for _, r in points], dtype=float),
                        grid,
                    )
                    for points in sessions.values()
                ]
            )
            mean, se, n = mean_and_standard_error(values)
            best = [max(r for _, r in points) for points in sessions.values()]
            curves.append(
                {
                    "learner": learner,
                    "sessions": len(sessions),
                    "mean": [_number(x) for x in mean],
                    "se": [_number(x) for x in se],
                    "n": [int(x) for x in n],
                    "past": {
                        f"{threshold:g}": round(sum(b >= threshold for b in best) / len(best), 4)
                        for threshold in thresholds
                    },
                }
            )
        environments.append(
            {"environment": environment, "episodes": [int(x) for x in grid], "learners": curves}
        )
    return {"thresholds": list(thresholds), "environments": environments}
