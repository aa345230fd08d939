"""Per-session measures and the paper's statistical comparisons.

A learning session *reaches* a threshold when one of its evaluations has a normalised return
at least that high; the episodes and actions it *required* are the cumulative counts at the
first such evaluation. The baseline learner is compared with each alternative on three
measures per threshold: how many sessions reached it (``success``), and the episodes and
actions required by the sessions that did. Within an environment these are Fisher's exact
test and Welch's t-test, corrected together with Benjamini-Yekutieli; across environments,
Fisher's exact test on the pooled counts and a type II ANOVA of an ordinary least squares
model with factors learner, environment and session position. All statistics are SciPy's
and statsmodels'.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from analysis.names import (
    environment_display,
    learner_display,
    order_environments,
    order_learners,
    threshold_label,
)

ALPHA = 0.05
NOT_TESTED = "N/A"  # the test column of a comparison that could not be tested
MEASURES = ("success", "episodes", "actions")
COMPARISON_COLUMNS = (
    "scope",
    "measure",
    "threshold",
    "baseline",
    "alternative",
    "baseline_value",
    "alternative_value",
    "test",
    "statistic",
    "p_value",
    "p_adjusted",
    "significant",
    "significant_adjusted",
    "note",
)
SESSION_INFO_COLUMNS = (
    "session_id",
    "participant_id",
    "domain",
    "environment",
    "learner",
    "position",
    "completed",
)


@dataclass(frozen=True)
class TestResult:
    """One test's outcome; ``p_value`` is None when the test could not be done, and ``note``
    then says why."""

    test: str
    statistic: float | None
    p_value: float | None
    note: str = ""


def reached_column(threshold: float) -> str:
    return f"reached_{threshold_label(threshold)}"


def required_column(measure: str, threshold: float) -> str:
    return f"{measure}_{threshold_label(threshold)}"


def session_measures(
    sessions: pd.DataFrame, evaluations: pd.DataFrame, thresholds: Sequence[float]
) -> pd.DataFrame:
    """One row per learning session: its evaluations, best and final normalised return, and
    per threshold whether it was reached and the cumulative episodes and actions at the first
    evaluation that reached it. Sessions without evaluations reach nothing."""
    ordered = evaluations.sort_values(["session_id", "update_index"], kind="stable")
    grouped = ordered.groupby("session_id", sort=False)["normalized_return"]
    summary = sessions.loc[:, list(SESSION_INFO_COLUMNS)].copy()
    ids = summary["session_id"]
    summary["evaluations"] = ids.map(grouped.size()).fillna(0).astype(np.int64)
    summary["final_normalized_return"] = ids.map(grouped.last())
    summary["best_normalized_return"] = ids.map(grouped.max())
    for threshold in thresholds:
        first = (
            ordered.loc[ordered["normalized_return"] >= threshold]
            .groupby("session_id", sort=False)
            .first()
        )
        summary[reached_column(threshold)] = ids.isin(first.index)
        for measure in ("episodes", "actions"):
            summary[required_column(measure, threshold)] = ids.map(first[measure]).astype("Int64")
    return summary.reset_index(drop=True)


def fisher_success(
    baseline_successes: int,
    baseline_sessions: int,
    alternative_successes: int,
    alternative_sessions: int,
) -> TestResult:
    """Fisher's exact test (two-sided) on [[baseline successes, failures], [alternative
    successes, failures]]; the statistic is SciPy's sample odds ratio."""
    from scipy.stats import fisher_exact

    if baseline_sessions == 0 or alternative_sessions == 0:
        which = "baseline" if baseline_sessions == 0 else "alternative"
        return TestResult("fisher_exact", None, None, f"no {which} sessions")
    table = [
        [baseline_successes, baseline_sessions - baseline_successes],
        [alternative_successes, alternative_sessions - alternative_successes],
    ]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # odds ratio of 0/0
        result = fisher_exact(table, alternative="two-sided")
    # Summing the table probabilities can overshoot 1 by a rounding error.
    return TestResult("fisher_exact", float(result.statistic), min(1.0, float(result.pvalue)))


def welch_t_test(baseline: Sequence[float], alternative: Sequence[float]) -> TestResult:
    """Welch's unpaired t-test (``ttest_ind(equal_var=False)``), two-sided; the statistic is
    t for baseline minus alternative. Needs two values per group and some variance."""
    from scipy.stats import ttest_ind

    b = np.asarray(baseline, dtype=float)
    a = np.asarray(alternative, dtype=float)
    b, a = b[~np.isnan(b)], a[~np.isnan(a)]  # sessions without a value
    if len(b) < 2 or len(a) < 2:
        return TestResult(
            "welch_t_test",
            None,
            None,
            f"too few values for a t-test: {len(b)} baseline and {len(a)} alternative "
            "(needs at least 2 in each)",
        )
    if np.ptp(b) == 0 and np.ptp(a) == 0:
        return TestResult(
            "welch_t_test",
            None,
            None,
            f"no variance in either group (every baseline value {b[0]:g}, every "
            f"alternative value {a[0]:g}); a t-test is undefined",
        )
    with warnings.catch_warnings():
        # SciPy warns of "precision loss" when a group's values are all equal; its variance
        # is then exactly 0 and the result exact.
        warnings.simplefilter("ignore", RuntimeWarning)
        result = ttest_ind(b, a, equal_var=False)
    return TestResult("welch_t_test", float(result.statistic), float(result.pvalue))


def anova_learner(frame: pd.DataFrame, learners: tuple[str, str]) -> TestResult:
    """The learner factor's F and p in a type II ANOVA of the OLS model
    ``value ~ C(learner) + C(environment) + C(position)`` over ``frame`` (columns value,
    learner, environment, position), comparing the two ``learners``.

    A factor with a single level is constant, so the model without it is the same fit; it is
    left out and the note says so.
    """
    import statsmodels.formula.api as smf
    from statsmodels.stats.anova import anova_lm

    test = "anova_type2"
    frame = frame.loc[frame["value"].notna()]  # sessions without a value
    counts = [int((frame["learner"] == name).sum()) for name in learners]
    if min(counts) < 2:
        described = " and ".join(
            f"{count} {learner_display(name)}" for name, count in zip(learners, counts, strict=True)
        )
        return TestResult(
            test,
            None,
            None,
            f"too few sessions for an ANOVA: {described} (needs at least 2 of each)",
        )
    frame = frame.loc[frame["learner"].isin(learners)]
    terms = ["C(learner)"]
    dropped = []
    for factor in ("environment", "position"):
        if frame[factor].nunique() > 1:
            terms.append(f"C({factor})")
        else:
            dropped.append(f"factor {factor} (one level: {frame[factor].iloc[0]})")
    data = frame.loc[:, ["value", "learner", "environment", "position"]].reset_index(drop=True)
    data["value"] = data["value"].astype(float)
    with warnings.catch_warnings():
        # A rank-deficient design is expected: in the paper's protocol each environment is
        # taught at fixed positions, so environment and position overlap. The learner's
        # test is unaffected as long as the learner is not confounded (checked below).
        warnings.simplefilter("ignore")
        model = smf.ols("value ~ " + " + ".join(terms), data=data).fit()
    note = f"{len(data)} sessions; factors: " + ", ".join(t[2:-1] for t in terms)
    if dropped:
        note += "; left out " + ", ".join(dropped)
    if model.df_resid < 1:
        return TestResult(test, None, None, f"no residual degrees of freedom ({note})")
    exog = np.asarray(model.model.exog)
    learner_columns = [
        i for i, name in enumerate(model.model.exog_names) if name.startswith("C(learner)")
    ]
    others = np.delete(exog, learner_columns, axis=1)
    rank = np.linalg.matrix_rank(exog)
    if rank < exog.shape[1]:
        note += "; environment and position overlap (rank-deficient design)"
    if rank == np.linalg.matrix_rank(others):
        return TestResult(
            test,
            None,
            None,
            f"the learner is confounded with the other factors; its effect cannot be "
            f"estimated ({note})",
        )
    # An exact fit leaves no error to test against (F would be infinite, or made of rounding
    # errors, which are of the order of 1e-32 times the sum of squared values).
    if model.ssr <= 1e-20 * float(model.uncentered_tss):
        return TestResult(
            test, None, None, f"the model fits exactly, no residual variance ({note})"
        )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        table = anova_lm(model, typ=2)
    statistic = float(table.loc["C(learner)", "F"])
    p_value = float(table.loc["C(learner)", "PR(>F)"])
    if not (math.isfinite(statistic) and math.isfinite(p_value)):
        return TestResult(test, None, None, f"the F-test is undefined ({note})")
    return TestResult(test, statistic, p_value, note)


def benjamini_yekutieli(p_values: Sequence[float]) -> np.ndarray:
    """Benjamini-Yekutieli adjusted p-values (SciPy's ``false_discovery_control``)."""
    from scipy.stats import false_discovery_control

    p = np.asarray(p_values, dtype=float)
    if p.size == 0:
        return p
    return np.asarray(false_discovery_control(p, method="by"), dtype=float)


def compare(
    summary: pd.DataFrame, thresholds: Sequence[float], baseline: str, fdr: float
) -> pd.DataFrame:
    """Every comparison of the baseline with an alternative: per environment (Fisher, Welch,
    then Benjamini-Yekutieli over all of them) and across all environments (Fisher on pooled
    counts, ANOVA). Columns ``COMPARISON_COLUMNS`` plus ``worse`` (the alternative did worse
    than the baseline: a lower success rate, or more episodes or actions)."""
    learners = order_learners(summary["learner"], baseline)
    alternatives = learners[1:]
    rows: list[dict[str, object]] = []
    for environment in order_environments(summary["environment"]):
        in_environment = summary.loc[summary["environment"] == environment]
        where = f"in {environment_display(environment)}"
        for measure in MEASURES:
            for threshold in thresholds:
                for alternative in alternatives:
                    rows.append(
                        _environment_comparison(
                            in_environment,
                            environment,
                            where,
                            measure,
                            threshold,
                            baseline,
                            alternative,
                        )
                    )
    environment_rows = [i for i, row in enumerate(rows) if row["p_value"] is not None]
    adjusted = benjamini_yekutieli([rows[i]["p_value"] for i in environment_rows])  # type: ignore[misc]
    for i, p_adjusted in zip(environment_rows, adjusted, strict=True):
        rows[i]["p_adjusted"] = float(p_adjusted)
        rows[i]["significant_adjusted"] = bool(p_adjusted <= fdr)
    for measure in MEASURES:
        for threshold in thresholds:
            for alternative in alternatives:
                rows.append(_pooled_comparison(summary, measure, threshold, baseline, alternative))
    # Object columns keep success counts as integers beside means, and None (written as an
    # empty cell) where there is no value.
    frame = pd.DataFrame(rows, columns=[*COMPARISON_COLUMNS, "worse"], dtype=object)
    frame["threshold"] = frame["threshold"].astype(float)
    frame["worse"] = frame["worse"].astype(bool)
    return frame


def _groups(
    frame: pd.DataFrame, baseline: str, alternative: str
) -> tuple[pd.DataFrame, pd.DataFrame]:
    return (
        frame.loc[frame["learner"] == baseline],
        frame.loc[frame["learner"] == alternative],
    )


def _environment_comparison(
    frame: pd.DataFrame,
    environment: str,
    where: str,
    measure: str,
    threshold: float,
    baseline: str,
    alternative: str,
) -> dict[str, object]:
    b, a = _groups(frame, baseline, alternative)
    reached = reached_column(threshold)
    if b.empty or a.empty:
        missing = learner_display(baseline if b.empty else alternative)
        result = TestResult(NOT_TESTED, None, None, f"no {missing} sessions {where}")
        return _row(
            environment, measure, threshold, baseline, alternative, (None, None), result, b, a
        )
    if measure == "success":
        result = fisher_success(int(b[reached].sum()), len(b), int(a[reached].sum()), len(a))
        values: tuple[float | None, float | None] = (
            int(b[reached].sum()),
            int(a[reached].sum()),
        )
    else:
        column = required_column(measure, threshold)
        b_values = b.loc[b[reached], column].astype(float)
        a_values = a.loc[a[reached], column].astype(float)
        result = welch_t_test(b_values, a_values)
        values = (_mean(b_values), _mean(a_values))
        if result.p_value is None and min(len(b_values), len(a_values)) < 2:
            result = _with_note(
                result,
                f"too few sessions for a t-test: {len(b_values)} {learner_display(baseline)} "
                f"and {len(a_values)} {learner_display(alternative)} sessions {where} reached "
                f"{threshold_label(threshold)}% (needs at least 2 in each)",
            )
    return _row(environment, measure, threshold, baseline, alternative, values, result, b, a)


def _pooled_comparison(
    summary: pd.DataFrame, measure: str, threshold: float, baseline: str, alternative: str
) -> dict[str, object]:
    # Pool only the environments where both learners were taught: elsewhere the learner
    # would be confounded with the environment.
    taught = summary.groupby("environment")["learner"].agg(set)
    shared = [e for e, learners in taught.items() if {baseline, alternative} <= learners]
    left_out = [
        environment_display(e)
        for e in order_environments(summary["environment"])
        if e not in shared and taught[e] & {baseline, alternative}
    ]
    b, a = _groups(summary.loc[summary["environment"].isin(shared)], baseline, alternative)
    reached = reached_column(threshold)
    if not shared:
        result = TestResult(
            NOT_TESTED,
            None,
            None,
            f"no environment has sessions of both {learner_display(baseline)} and "
            f"{learner_display(alternative)}",
        )
        return _row("all", measure, threshold, baseline, alternative, (None, None), result, b, a)
    if measure == "success":
        result = fisher_success(int(b[reached].sum()), len(b), int(a[reached].sum()), len(a))
        values: tuple[float | None, float | None] = (
            int(b[reached].sum()),
            int(a[reached].sum()),
        )
    else:
        column = required_column(measure, threshold)
        both = pd.concat([b, a])
        both = both.loc[both[reached]]
        frame = pd.DataFrame(
            {
                "value": both[column].astype(float),
                "learner": both["learner"],
                "environment": both["environment"],
                "position": both["position"],
            }
        )
        result = anova_learner(frame, (baseline, alternative))
        if result.p_value is None:
            result = _with_note(
                result, f"over sessions that reached {threshold_label(threshold)}%: {result.note}"
            )
        values = (
            _mean(b.loc[b[reached], column].astype(float)),
            _mean(a.loc[a[reached], column].astype(float)),
        )
    if left_out:
        result = _with_note(
            result,
            "; ".join(
                part
                for part in (
                    result.note,
                    f"left out {', '.join(left_out)} (not both learners taught there)",
                )
                if part
            ),
        )
    return _row("all", measure, threshold, baseline, alternative, values, result, b, a)


def _row(
    scope: str,
    measure: str,
    threshold: float,
    baseline: str,
    alternative: str,
    values: tuple[float | None, float | None],
    result: TestResult,
    b: pd.DataFrame,
    a: pd.DataFrame,
) -> dict[str, object]:
    reached = reached_column(threshold)
    if b.empty or a.empty:
        worse = better = False
        counts = ""
    elif measure == "success":
        b_rate, a_rate = b[reached].mean(), a[reached].mean()
        worse = bool(a_rate < b_rate)
        better = bool(a_rate > b_rate)
        counts = (
            f"{int(b[reached].sum())} of {len(b)} vs {int(a[reached].sum())} of {len(a)} "
            f"sessions reached {threshold_label(threshold)}%"
        )
    else:
        b_value, a_value = values
        worse = b_value is not None and a_value is not None and a_value > b_value
        better = b_value is not None and a_value is not None and a_value < b_value
        counts = ""
    note_parts = [part for part in (counts, result.note) if part]
    if result.p_value is not None:
        note_parts.append(
            "alternative worse" if worse else "alternative better" if better else "no difference"
        )
    return {
        "scope": scope,
        "measure": measure,
        "threshold": threshold,
        "baseline": baseline,
        "alternative": alternative,
        "baseline_value": values[0],
        "alternative_value": values[1],
        "test": result.test if result.p_value is not None else NOT_TESTED,
        "statistic": result.statistic,
        "p_value": result.p_value,
        "p_adjusted": None,
        "significant": None if result.p_value is None else bool(result.p_value <= ALPHA),
        "significant_adjusted": None,
        "note": "; ".join(note_parts),
        "worse": bool(worse) and result.p_value is not None,
    }


def _with_note(result: TestResult, note: str) -> TestResult:
    return TestResult(result.test, result.statistic, result.p_value, note)


def _mean(values: pd.Series) -> float | None:
    return float(values.mean()) if len(values) else None


def table1_values(
    summary: pd.DataFrame, thresholds: Sequence[float], baseline: str
) -> pd.DataFrame:
    """Table 1's numbers: per environment and learner (in the paper's order), the total
    sessions, and per threshold the sessions that reached it and the mean episodes and
    actions they required (None where no session reached it)."""
    rows = []
    learners = order_learners(summary["learner"], baseline)
    for environment in order_environments(summary["environment"]):
        in_environment = summary.loc[summary["environment"] == environment]
        for learner in learners:
            group = in_environment.loc[in_environment["learner"] == learner]
            if group.empty:
                continue
            row: dict[str, object] = {
                "environment": environment,
                "learner": learner,
                "sessions": len(group),
            }
            for threshold in thresholds:
                reached = group.loc[group[reached_column(threshold)]]
                row[reached_column(threshold)] = len(reached)
                for measure in ("episodes", "actions"):
                    column = required_column(measure, threshold)
                    row[column] = _mean(reached[column].astype(float))
            rows.append(row)
    return pd.DataFrame(rows)
