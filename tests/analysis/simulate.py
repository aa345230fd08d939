"""Studies simulated from a known model, for checking the tests' level and power.

Each participant teaches the three learners in each of two environments, in a random order
(positions 0-2 in the first environment, 3-5 in the second), as in the paper's design. A
participant's skill is drawn once and shared by all six sessions: the chance that an episode
brings the agent to the threshold is ``logistic(-1.6 + skill + environment - effect[learner])``,
so a session's episodes to the threshold are geometric, and a session stopped after
``BUDGET`` episodes without reaching it is censored there.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from analysis.stats import reached_column, required_column

LEARNERS = ("bam", "model-based", "cloning")
ENVIRONMENTS = ("two-rooms", "doorway")
ENVIRONMENT_EFFECT = {"two-rooms": 0.4, "doorway": -0.4}
BUDGET = 10  # episodes a session lasts without reaching the threshold
THRESHOLD = 0.5
SKILL_SD = 1.5  # participants of widely different skill


def simulate_study(
    rng: np.random.Generator,
    participants: int,
    effect: float = 0.0,
    *,
    missing: float = 0.0,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """``(summary, evaluations)`` as ``analysis.stats.session_measures`` and the export give
    them, for one threshold (``THRESHOLD``). ``effect`` lowers Behavioral Cloning's chance per
    episode on the logit scale (the other learners are alike); ``missing`` is the share of
    sessions dropped at random (participants who left, sessions excluded), which unbalances
    the design."""
    rows = []
    for p in range(participants):
        skill = rng.normal(0.0, SKILL_SD)
        for offset, environment in ((0, ENVIRONMENTS[0]), (3, ENVIRONMENTS[1])):
            for slot, learner in enumerate(rng.permutation(LEARNERS)):
                logit = -1.6 + skill + ENVIRONMENT_EFFECT[environment]
                logit -= effect if learner == "cloning" else 0.0
                chance = 1.0 / (1.0 + np.exp(-logit))
                episodes = int(rng.geometric(chance))
                reached = episodes <= BUDGET
                rows.append(
                    {
                        "session_id": f"p{p}-{environment}-{learner}",
                        "participant_id": f"p{p}",
                        "environment": environment,
                        "learner": str(learner),
                        "position": offset + slot,
                        "evaluations": BUDGET,
                        reached_column(THRESHOLD): reached,
                        required_column("episodes", THRESHOLD): episodes if reached else None,
                        required_column("actions", THRESHOLD): 12 * episodes if reached else None,
                    }
                )
    summary = pd.DataFrame(rows)
    if missing:
        summary = summary.loc[rng.random(len(summary)) >= missing].reset_index(drop=True)
    for measure in ("episodes", "actions"):
        column = required_column(measure, THRESHOLD)
        summary[column] = summary[column].astype("Int64")
    evaluations = pd.DataFrame(
        {
            "session_id": summary["session_id"],
            "episodes": BUDGET,
            "actions": 12 * BUDGET,
        }
    )
    return summary, evaluations
