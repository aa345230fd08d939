"""The paper's names for the learners, kept apart from the learners' code so that a command can
name them without loading NumPy's and SciPy's learning stack (``bam-study --help`` stays fast).
``server.learners.DISPLAY_NAMES`` is this table; environments' names are ``server.domains.title``.
"""

from __future__ import annotations

# Learner name (as in the registry, the study file and the export) -> the paper's name, in the
# order the paper's tables list them.
LEARNER_DISPLAY_NAMES: dict[str, str] = {
    "bam": "BAM",
    "model-based": "Model-Based IRL",
    "global-cost": "Model-Based IRL (global cost)",
    "cloning": "Behavioral Cloning",
}
