"""The whole analysis of one study, from validated tables to everything the outputs show."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from analysis.design_results import DesignResults, design_analysis
from analysis.flow import ParticipantFlow
from analysis.names import LEARNERS, order_environments, order_learners
from analysis.options import (
    DEFAULT_BASELINE,
    DEFAULT_FDR,
    DEFAULT_THRESHOLDS,
    InputError,
    check_fdr,
    check_thresholds,
)
from analysis.stats import compare, session_measures, table1_values


@dataclass(frozen=True)
class Analysis:
    baseline: str
    thresholds: tuple[float, ...]
    fdr: float
    learners: tuple[str, ...]  # baseline first
    environments: tuple[str, ...]  # in the paper's order
    summary: pd.DataFrame  # one row per learning session (stats.session_measures)
    evaluations: pd.DataFrame
    comparisons: pd.DataFrame  # stats.compare
    table1: pd.DataFrame  # stats.table1_values
    notes: tuple[str, ...]  # remarks about the data, for the reader of the results
    # The design-respecting comparisons beside the paper's (design_results.design_analysis).
    design: DesignResults | None = None
    # Arrived to analysed, from the export's statuses (analysis.flow); None without them.
    flow: ParticipantFlow | None = None

    @property
    def alternatives(self) -> tuple[str, ...]:
        return self.learners[1:]

    @property
    def sessions_without_evaluations(self) -> int:
        return int((self.summary["evaluations"] == 0).sum())

    @property
    def environment_tests(self) -> int:
        """How many environment-specific comparisons had a p-value (the family that the
        Benjamini-Yekutieli correction covers)."""
        scoped = self.comparisons.loc[self.comparisons["scope"] != "all"]
        return int(scoped["p_value"].notna().sum())

    def comparison(
        self, scope: str, measure: str, threshold: float, alternative: str
    ) -> pd.Series | None:
        c = self.comparisons
        match = c.loc[
            (c["scope"] == scope)
            & (c["measure"] == measure)
            & (c["threshold"] == threshold)
            & (c["alternative"] == alternative)
        ]
        return None if match.empty else match.iloc[0]

    def marks(
        self, environment: str, measure: str, threshold: float, learner: str
    ) -> tuple[bool, bool]:
        """(significantly worse than the baseline at ALPHA, and still so after the
        Benjamini-Yekutieli correction) for one cell of Table 1."""
        row = self.comparison(environment, measure, threshold, learner)
        if row is None or not (_flag(row["worse"]) and _flag(row["significant"])):
            return False, False
        return True, _flag(row["significant_adjusted"])


def _flag(value: object) -> bool:
    """True for a true boolean; False for false, None and NaN (a test not done)."""
    return isinstance(value, bool | np.bool_) and bool(value)


def analyze(
    sessions: pd.DataFrame,
    evaluations: pd.DataFrame,
    *,
    thresholds: Sequence[float] = DEFAULT_THRESHOLDS,
    fdr: float = DEFAULT_FDR,
    baseline: str = DEFAULT_BASELINE,
    notes: Iterable[str] = (),
    flow: ParticipantFlow | None = None,
) -> Analysis:
    """Everything the outputs show, from tables validated by ``analysis.data`` (and the
    participant flow of the same export, ``analysis.flow.participant_flow``)."""
    thresholds = check_thresholds(thresholds)
    fdr = check_fdr(fdr)
    if baseline not in LEARNERS:
        raise InputError(f"--baseline: unknown learner {baseline!r} (known: {', '.join(LEARNERS)})")
    if not (sessions["learner"] == baseline).any():
        present = ", ".join(order_learners(sessions["learner"], baseline))
        raise InputError(
            f"--baseline: no learning sessions of {baseline!r} in the data "
            f"(learners present: {present})"
        )
    summary = session_measures(sessions, evaluations, thresholds)
    notes = list(notes)
    without = int((summary["evaluations"] == 0).sum())
    if without:
        notes.append(
            f"{without} learning session{'s' if without != 1 else ''} had no evaluations; "
            f"{'they count' if without != 1 else 'it counts'} in the total sessions and "
            "reached no threshold"
        )
    incomplete = int((~summary["completed"]).sum())
    if incomplete:
        notes.append(
            f"{incomplete} learning session{'s were' if incomplete != 1 else ' was'} not "
            "completed; included all the same"
        )
    return Analysis(
        baseline=baseline,
        thresholds=thresholds,
        fdr=fdr,
        learners=tuple(order_learners(summary["learner"], baseline)),
        environments=tuple(order_environments(summary["environment"])),
        summary=summary,
        evaluations=evaluations,
        comparisons=compare(summary, thresholds, baseline, fdr),
        table1=table1_values(summary, thresholds, baseline),
        notes=tuple(notes),
        design=design_analysis(summary, evaluations, thresholds, baseline, fdr),
        flow=flow,
    )
