"""The design-respecting comparisons of a study, beside the paper's (``analysis.stats``).

Every comparison of the baseline with an alternative, per environment and over all of them
(``scope`` "all"), at each threshold:

- success: the exact McNemar mid-p test on the blocks (``analysis.design``), with the paired
  risk difference, the conditional odds ratio and the permutation p-value; and the GEE model's
  population-averaged odds ratio (``analysis.models``);
- episodes and actions to the threshold: the Cox model stratified by block, its hazard ratio
  (``analysis.survival``), beside each learner's median count.

The Benjamini-Yekutieli correction covers the environment-specific McNemar and Cox p-values
(the family of the design's primary tests, as the paper's correction covers its
environment-specific tests); the GEE model and the permutation test are their checks. Each
row ends in a sentence that says what was found and how sure it is.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from analysis import design, models, survival
from analysis.names import order_environments, order_learners
from analysis.sentences import comparison_sentence
from analysis.stats import ALPHA, benjamini_yekutieli

PRIMARY_TESTS = ("mcnemar_midp", "cox_stratified")
DESIGN_COLUMNS = (
    "scope",
    "measure",
    "threshold",
    "baseline",
    "alternative",
    "test",
    "blocks",
    "both",
    "baseline_only",
    "alternative_only",
    "neither",
    "baseline_value",
    "alternative_value",
    "risk_difference",
    "risk_difference_low",
    "risk_difference_high",
    "odds_ratio",
    "odds_ratio_low",
    "odds_ratio_high",
    "hazard_ratio",
    "hazard_ratio_low",
    "hazard_ratio_high",
    "p_value",
    "p_permutation",
    "p_adjusted",
    "significant",
    "significant_adjusted",
    "note",
    "sentence",
)
OMNIBUS_COLUMNS = (
    "scope",
    "threshold",
    "learners",
    "blocks",
    "cochran_q",
    "df",
    "p_value",
    "p_permutation",
    "permutations",
    "permutation_blocks",
)
MEDIAN_COLUMNS = (
    "scope",
    "measure",
    "threshold",
    "learner",
    "sessions",
    "reached",
    "median",
    "median_low",
    "median_high",
)


@dataclass(frozen=True)
class DesignResults:
    comparisons: pd.DataFrame  # DESIGN_COLUMNS
    omnibus: pd.DataFrame  # OMNIBUS_COLUMNS
    medians: pd.DataFrame  # MEDIAN_COLUMNS
    family: int  # p-values the correction covered


def design_analysis(
    summary: pd.DataFrame,
    evaluations: pd.DataFrame,
    thresholds: Sequence[float],
    baseline: str,
    fdr: float,
    *,
    permutations: int = design.PERMUTATIONS,
) -> DesignResults:
    """Every design-respecting comparison (the module's docstring)."""
    learners = order_learners(summary["learner"], baseline)
    alternatives = learners[1:]
    scopes = [
        (e, summary.loc[summary["environment"] == e])
        for e in order_environments(summary["environment"])
    ]
    scopes.append(("all", summary))
    rows: list[dict[str, object]] = []
    omnibus: list[dict[str, object]] = []
    medians: list[dict[str, object]] = []
    for scope, frame in scopes:
        pooled = scope == "all"
        for threshold in thresholds:
            blocks = design.block_outcomes(frame, threshold)
            present = [name for name in alternatives if name in blocks]
            permuted = (
                design.permutation_test(blocks, baseline, present, permutations=permutations)
                if baseline in blocks and present
                else None
            )
            omnibus.append(_omnibus(scope, threshold, blocks, [baseline, *present], permuted))
            gee = models.gee_odds_ratios(frame, threshold, baseline, alternatives, pooled=pooled)
            for alternative in alternatives:
                key = (scope, "success", threshold, baseline, alternative)
                rows.append(_mcnemar_row(key, blocks, permuted))
                rows.append(_gee_row(key, gee[alternative]))
            for measure in ("episodes", "actions"):
                times = survival.event_times(frame, evaluations, measure, threshold)
                middle = {}
                for learner in learners:
                    found = survival.median_time(times.loc[times["learner"] == learner])
                    middle[learner] = found.median
                    medians.append(_median_row(scope, measure, threshold, learner, found))
                for alternative in alternatives:
                    key = (scope, measure, threshold, baseline, alternative)
                    hazard = survival.cox_stratified(times, baseline, alternative)
                    rows.append(_cox_row(key, hazard, middle[baseline], middle[alternative]))
    comparisons = pd.DataFrame(rows, columns=list(DESIGN_COLUMNS), dtype=object)
    family = _correct(comparisons, fdr)
    comparisons["threshold"] = comparisons["threshold"].astype(float)
    comparisons["sentence"] = [
        comparison_sentence(row, fdr, family) for _, row in comparisons.iterrows()
    ]
    return DesignResults(
        comparisons=comparisons,
        omnibus=pd.DataFrame(omnibus, columns=list(OMNIBUS_COLUMNS)),
        medians=pd.DataFrame(medians, columns=list(MEDIAN_COLUMNS)),
        family=family,
    )


def _correct(comparisons: pd.DataFrame, fdr: float) -> int:
    """Benjamini-Yekutieli over the environment-specific primary p-values, in place."""
    chosen = (
        (comparisons["scope"] != "all")
        & comparisons["test"].isin(PRIMARY_TESTS)
        & comparisons["p_value"].notna()
    )
    index = comparisons.index[chosen]
    adjusted = benjamini_yekutieli(comparisons.loc[index, "p_value"].astype(float).tolist())
    for i, value in zip(index, adjusted, strict=True):
        comparisons.at[i, "p_adjusted"] = float(value)
        comparisons.at[i, "significant_adjusted"] = bool(value <= fdr)
    return len(index)


def _base(key: tuple[str, str, float, str, str], test: str) -> dict[str, object]:
    scope, measure, threshold, baseline, alternative = key
    row: dict[str, object] = dict.fromkeys(DESIGN_COLUMNS)
    row.update(
        scope=scope,
        measure=measure,
        threshold=threshold,
        baseline=baseline,
        alternative=alternative,
        test=test,
        note="",
    )
    return row


def _finite(value: float) -> float | None:
    return float(value) if value is not None and np.isfinite(value) else None


def _with_p(row: dict[str, object], p_value: float | None) -> dict[str, object]:
    row["p_value"] = p_value
    row["significant"] = None if p_value is None else bool(p_value <= ALPHA)
    return row


def _mcnemar_row(
    key: tuple[str, str, float, str, str],
    blocks: pd.DataFrame,
    permuted: design.Permutation | None,
) -> dict[str, object]:
    row = _base(key, "mcnemar_midp")
    baseline, alternative = key[3], key[4]
    if baseline not in blocks or alternative not in blocks:
        row["blocks"] = 0
        row["note"] = "no block has a session of both learners"
        return _with_p(row, None)
    paired = design.paired_counts(blocks, baseline, alternative)
    row.update(
        blocks=paired.blocks,
        both=paired.both,
        baseline_only=paired.baseline_only,
        alternative_only=paired.alternative_only,
        neither=paired.neither,
        baseline_value=paired.both + paired.baseline_only,
        alternative_value=paired.both + paired.alternative_only,
    )
    if paired.blocks == 0:
        row["note"] = "no block has a session of both learners"
        return _with_p(row, None)
    rd = design.risk_difference(paired)
    ratio = design.conditional_odds_ratio(paired)
    row.update(
        risk_difference=rd[0],
        risk_difference_low=rd[1],
        risk_difference_high=rd[2],
        odds_ratio=_finite(ratio[0]),
        odds_ratio_low=_finite(ratio[1]),
        odds_ratio_high=_finite(ratio[2]),
    )
    if permuted is not None and alternative in permuted.p_pairs:
        row["p_permutation"] = permuted.p_pairs[alternative]
    if paired.baseline_only + paired.alternative_only == 0:
        row["note"] = "no discordant block: the odds ratio is undefined"
    elif np.isinf(ratio[0]):
        row["note"] = "no block where only the baseline reached it: the odds ratio is infinite"
    return _with_p(row, design.mcnemar_midp(paired.baseline_only, paired.alternative_only))


def _gee_row(key: tuple[str, str, float, str, str], found: models.OddsRatio) -> dict[str, object]:
    row = _base(key, "gee_logistic")
    row.update(
        odds_ratio=found.ratio,
        odds_ratio_low=found.low,
        odds_ratio_high=found.high,
        note=found.note,
    )
    return _with_p(row, found.p_value)


def _cox_row(
    key: tuple[str, str, float, str, str],
    found: survival.HazardRatio,
    baseline_median: float,
    alternative_median: float,
) -> dict[str, object]:
    row = _base(key, "cox_stratified")
    row.update(
        blocks=found.blocks,
        baseline_value=_finite(baseline_median),
        alternative_value=_finite(alternative_median),
        hazard_ratio=found.ratio,
        hazard_ratio_low=found.low,
        hazard_ratio_high=found.high,
        note=found.note,
    )
    return _with_p(row, found.p_value)


def _median_row(
    scope: str, measure: str, threshold: float, learner: str, found: survival.Median
) -> dict[str, object]:
    return {
        "scope": scope,
        "measure": measure,
        "threshold": threshold,
        "learner": learner,
        "sessions": found.sessions,
        "reached": found.events,
        "median": _finite(found.median),
        "median_low": _finite(found.low),
        "median_high": _finite(found.high),
    }


def _omnibus(
    scope: str,
    threshold: float,
    blocks: pd.DataFrame,
    learners: Sequence[str],
    permuted: design.Permutation | None,
) -> dict[str, object]:
    q = design.cochran_q(blocks, learners) if all(n in blocks for n in learners) else None
    return {
        "scope": scope,
        "threshold": threshold,
        "learners": " ".join(learners),
        "blocks": None if q is None else q.blocks,
        "cochran_q": None if q is None else q.statistic,
        "df": None if q is None else q.df,
        "p_value": None if q is None else q.p_value,
        "p_permutation": None if permuted is None else permuted.p_all,
        "permutations": None if permuted is None else permuted.permutations,
        "permutation_blocks": None if permuted is None else permuted.blocks,
    }
