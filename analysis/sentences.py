"""A plain sentence per design-respecting comparison: what was found and how sure it is.

How sure, by the p-value: at most 0.001 "strong evidence", 0.01 "good evidence", 0.05 "some
evidence", 0.1 "weak evidence", above that "no clear evidence". The environment-specific
primary tests add whether the difference stays significant after the Benjamini-Yekutieli
correction.
"""

from __future__ import annotations

import pandas as pd

from analysis.names import environment_display, learner_display, threshold_label

EVIDENCE = ((0.001, "strong evidence"), (0.01, "good evidence"), (0.05, "some evidence"))
WEAK = 0.1


def evidence(p_value: float) -> str:
    for bound, words in EVIDENCE:
        if p_value <= bound:
            return words
    return "weak evidence" if p_value <= WEAK else "no clear evidence"


def number(value: object) -> str:
    """A count for a sentence: as it is, to 3 significant digits."""
    return f"{float(value):.3g}"  # type: ignore[arg-type]


def ratio(value: object) -> str:
    """A ratio for a sentence: two decimals, "infinity" for infinity."""
    value = float(value)  # type: ignore[arg-type]
    return "infinity" if value == float("inf") else f"{value:.2f}"


def p_text(p_value: float) -> str:
    return "p < 0.001" if p_value < 0.001 else f"p = {p_value:.3f}"


def comparison_sentence(row: pd.Series, fdr: float, family: int) -> str:
    """The sentence of one row of ``design_results.DESIGN_COLUMNS``."""
    scope = (
        "over all environments"
        if row["scope"] == "all"
        else (f"in {environment_display(str(row['scope']))}")
    )
    baseline = learner_display(str(row["baseline"]))
    alternative = learner_display(str(row["alternative"]))
    label = f"{threshold_label(float(row['threshold']))}%"
    head = f"{alternative} against {baseline} {scope}, {row['measure']} at {label}"
    if row["p_value"] is None or pd.isna(row["p_value"]):
        return f"{head}: not tested ({row['note'] or 'no data'})."
    p_value = float(row["p_value"])
    if row["test"] == "mcnemar_midp":
        found = (
            f"of {row['blocks']} participants' blocks with both, {alternative} reached it in "
            f"{row['alternative_value']} and {baseline} in {row['baseline_value']} (risk "
            f"difference {_points(row['risk_difference'])} points, 95% CI "
            f"{_points(row['risk_difference_low'])} to {_points(row['risk_difference_high'])}); "
            f"exact McNemar mid-{p_text(p_value)}"
        )
        direction = _direction(row["risk_difference"], "succeeds more often", "succeeds less often")
    elif row["test"] == "gee_logistic":
        found = (
            f"odds of reaching it {ratio(row['odds_ratio'])} times {baseline}'s (95% CI "
            f"{ratio(row['odds_ratio_low'])} to {ratio(row['odds_ratio_high'])}; GEE, "
            f"{p_text(p_value)})"
        )
        direction = _direction(
            float(row["odds_ratio"]) - 1, "succeeds more often", "succeeds less often"
        )
    else:
        medians = ""
        if row["baseline_value"] is not None and row["alternative_value"] is not None:
            medians = (
                f"; median {number(row['alternative_value'])} against "
                f"{number(row['baseline_value'])} {row['measure']}"
            )
        found = (
            f"reaches it {ratio(row['hazard_ratio'])} times as fast per {row['measure'][:-1]} "
            f"(hazard ratio, 95% CI {ratio(row['hazard_ratio_low'])} to "
            f"{ratio(row['hazard_ratio_high'])}; stratified Cox, {p_text(p_value)}{medians})"
        )
        direction = _direction(
            float(row["hazard_ratio"]) - 1,
            f"needs fewer {row['measure']}",
            f"needs more {row['measure']}",
        )
    sure = evidence(p_value)
    verdict = (
        "no clear evidence of a difference"
        if sure == "no clear evidence"
        else f"{sure} that {alternative} {direction} than {baseline}"
    )
    if row["p_adjusted"] is not None and not pd.isna(row["p_adjusted"]):
        kept = "still" if row["significant_adjusted"] else "not"
        verdict += (
            f"; {kept} significant after the correction for {family} environment-specific "
            f"tests (adjusted p = {float(row['p_adjusted']):.3f}, false discovery rate {fdr:g})"
        )
    return f"{head}: {found}: {verdict}."


def _direction(signed: object, better: str, worse: str) -> str:
    """``better`` when the alternative does better (``signed`` > 0), else ``worse``."""
    return better if float(signed) > 0 else worse  # type: ignore[arg-type]


def _points(value: object) -> str:
    return f"{100 * float(value):+.0f}"  # type: ignore[arg-type]
