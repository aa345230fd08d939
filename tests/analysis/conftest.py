"""A small study, written as an export folder the way `bam-study export` writes one."""

from __future__ import annotations

import csv
from collections.abc import Collection, Sequence
from pathlib import Path

import pytest

from analysis.data import EPISODE_COLUMNS, EVALUATION_COLUMNS, SESSION_COLUMNS

# (session_id, participant_id, environment, learner, position,
#  evaluations as (episodes, actions, normalized_return) in update order)
Session = tuple[str, str, str, str, int, Sequence[tuple[int, int, float]]]

DOMAINS = {"two-rooms": "navigation", "doorway": "navigation"}


def curve(reach_50: int | None, reach_80: int | None, last: int, actions_per: int = 10):
    """Evaluations after episodes 1..last: 0.2 until ``reach_50``, 0.6 from then, 0.9 from
    ``reach_80``; actions are ``actions_per`` per episode plus the episode number (so that
    the numbers of actions differ from the numbers of episodes times a constant)."""
    points = []
    for episode in range(1, last + 1):
        value = 0.2
        if reach_50 is not None and episode >= reach_50:
            value = 0.6
        if reach_80 is not None and episode >= reach_80:
            value = 0.9
        points.append((episode, episode * actions_per + episode * episode, value))
    return points


# Four navigation participants, each teaching the three learners in Two Rooms (positions 0-2,
# in a rotating order) and then in Doorway (positions 3-5).
_PLAN = {
    # environment: learner: per participant (reach_50, reach_80, last episode)
    "two-rooms": {
        "bam": [(2, 3, 5), (2, 3, 5), (3, 4, 6), (3, 4, 6)],
        "model-based": [(3, 6, 8), (4, 7, 8), (4, None, 8), (5, None, 8)],
        "cloning": [(8, None, 9), (9, None, 10), (None, None, 10), (None, None, 10)],
    },
    "doorway": {
        "bam": [(2, 4, 6), (3, 5, 6), (3, 5, 6), (4, 6, 7)],
        "model-based": [(2, 5, 6), (3, None, 6), (4, None, 6), (3, None, 6)],
        "cloning": [(7, None, 8), (7, None, 8), (8, None, 9), None],  # None: no evaluations
    },
}


def small_study() -> list[Session]:
    sessions: list[Session] = []
    number = 0
    for p in range(4):
        participant = f"p{p + 1}"
        for offset, environment in ((0, "two-rooms"), (3, "doorway")):
            learners = list(_PLAN[environment])
            order = learners[p % 3 :] + learners[: p % 3]
            for slot, learner in enumerate(order):
                number += 1
                plan = _PLAN[environment][learner][p]
                points = [] if plan is None else curve(*plan)
                sessions.append(
                    (f"s{number:02d}", participant, environment, learner, offset + slot, points)
                )
    return sessions


def write_csv(path: Path, columns: Sequence[str], rows: Sequence[dict[str, object]]) -> None:
    with path.open("w", newline="", encoding="utf-8") as file:
        writer = csv.DictWriter(file, fieldnames=list(columns))
        writer.writeheader()
        writer.writerows(rows)


def write_export(
    folder: Path,
    sessions: Sequence[Session],
    *,
    participants: dict[str, str] | None = None,
    excluded: Collection[str] = (),
    episodes: Sequence[dict[str, object]] = (),
) -> Path:
    """Write sessions.csv, evaluations.csv and episodes.csv (with ``episodes``' rows only; the
    analysis reads it for empty episodes), and participants.csv into ``folder``: a status per
    participant (``participants``; by default every participant of ``sessions`` submitted the
    study, as after a whole study) and whether the experimenter excluded them."""
    folder.mkdir(parents=True, exist_ok=True)
    session_rows = []
    evaluation_rows = []
    for session_id, participant, environment, learner, position, points in sessions:
        shared = {
            "session_id": session_id,
            "participant_id": participant,
            "domain": DOMAINS.get(environment, "navigation"),
            "environment": environment,
            "learner": learner,
            "position": position,
        }
        session_rows.append(
            {
                **shared,
                "started_at": "2024-05-01T10:00:00Z",
                "finished_at": "2024-05-01T10:05:00Z",
                "completed": "true",
            }
        )
        for update, (count, actions, value) in enumerate(points):
            evaluation_rows.append(
                {
                    **shared,
                    "update_index": update,
                    "episodes": count,
                    "actions": actions,
                    "normalized_return": value,
                }
            )
    write_csv(folder / "sessions.csv", SESSION_COLUMNS, session_rows)
    write_csv(folder / "evaluations.csv", EVALUATION_COLUMNS, evaluation_rows)
    write_csv(folder / "episodes.csv", EPISODE_COLUMNS, episodes)
    if participants is None:
        participants = {session[1]: "submitted" for session in sessions}
    write_csv(
        folder / "participants.csv",
        ("participant_id", "status", "excluded"),
        [
            {"participant_id": p, "status": s, "excluded": str(p in excluded).lower()}
            for p, s in participants.items()
        ],
    )
    return folder


@pytest.fixture
def export(tmp_path: Path) -> Path:
    return write_export(tmp_path / "export", small_study())
