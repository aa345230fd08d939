"""The design-respecting comparisons' outputs: their CSV files, ``design.md`` (the report's
section on them) and their Kaplan-Meier figures, beside the paper's tables."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from analysis.design_results import (
    DESIGN_COLUMNS,
    MEDIAN_COLUMNS,
    OMNIBUS_COLUMNS,
    PRIMARY_TESTS,
    DesignResults,
)
from analysis.models import METHOD
from analysis.names import environment_display, learner_display, threshold_label
from analysis.results import Analysis
from analysis.survival_plot import save_survival_curves

DESIGN_FILES = {
    "design_comparisons.csv": DESIGN_COLUMNS,
    "design_omnibus.csv": OMNIBUS_COLUMNS,
    "survival_medians.csv": MEDIAN_COLUMNS,
}


def describe_design_files() -> str:
    """What each design-respecting output holds (a part of the outputs' README)."""
    return f"""- `design.md`: the comparisons that respect the study's design, in words: a sentence per
  comparison saying what was found and how sure it is, then the omnibus tests and the median
  counts. A *block* is one participant's sessions in one environment; every test here compares
  the learners within blocks, so the teacher's skill cancels out.
- `design_comparisons.csv`: one row per comparison of the baseline with an alternative, per
  environment and over `all`. `test` is `mcnemar_midp` (success: exact McNemar mid-p on the
  blocks with both learners; `both`, `baseline_only`, `alternative_only`, `neither` count
  them; `risk_difference` is the alternative's success rate minus the baseline's over those
  blocks with Agresti-Min's 95% interval; `odds_ratio` the conditional odds ratio
  `alternative_only / baseline_only` with its exact interval; `p_permutation` the p-value of
  shuffling the learner labels within blocks), `gee_logistic` (success: {METHOD};
  `odds_ratio` population averaged) or `cox_stratified` (episodes or actions to the
  threshold as time to an event, sessions that never reached it censored at their last
  evaluation: a Cox model stratified by block with the position as covariate, Efron's ties;
  `hazard_ratio` above 1 means the alternative reaches it sooner; `baseline_value` and
  `alternative_value` are the Kaplan-Meier median counts, empty when fewer than half reached
  it). `p_adjusted`: Benjamini-Yekutieli over the environment-specific {" and ".join(PRIMARY_TESTS)}
  p-values; `sentence`: the comparison in words. `note` says why a test could not be done.
- `design_omnibus.csv`: per scope and threshold, Cochran's Q over every learner on the blocks
  that have a session of each (`cochran_q`, `df`, chi-squared `p_value`) and the permutation
  test of every learner at once (`p_permutation`, from `permutations` shuffles within
  `permutation_blocks` blocks).
- `survival_medians.csv`: per scope, measure, threshold and learner, the taught sessions, how
  many reached the threshold, and the Kaplan-Meier median count with its 95% interval
  (complementary log-log; empty where not estimable, an open upper end is empty).
- `survival_episodes.png|svg`, `survival_actions.png|svg`: the Kaplan-Meier curves, the share
  of each learner's sessions not yet at each threshold after each count, one panel per
  environment and threshold.
"""


def design_markdown(analysis: Analysis) -> str:
    """``design.md``: the sentences, then the omnibus tests and the medians as tables."""
    design = _results(analysis)
    parts = [
        "# Comparisons within participants\n",
        "Each participant taught every learner in each environment of their domain, so the "
        "learner varies within a participant's *block* (their sessions in one environment). "
        "These tests compare the learners within blocks; the paper's tables (`table1.md`) "
        "treat every session as independent. The correction for multiple comparisons covers "
        f"the {design.family} environment-specific McNemar and Cox p-values (Benjamini-"
        f"Yekutieli, false discovery rate {analysis.fdr:g}).\n",
    ]
    comparisons = design.comparisons
    for scope in [*analysis.environments, "all"]:
        title = "All environments" if scope == "all" else environment_display(scope)
        rows = comparisons.loc[comparisons["scope"] == scope]
        if rows.empty:
            continue
        parts.append(f"## {title}\n")
        parts.extend(f"- {sentence}" for sentence in rows["sentence"])
        parts.append("")
    parts.append("## Every learner at once\n")
    parts.append(_omnibus_table(design.omnibus, analysis))
    parts.append("\n## Median counts to each threshold (Kaplan-Meier)\n")
    parts.append(_median_table(design.medians, analysis))
    return "\n".join(parts) + "\n"


def readme_section(analysis: Analysis) -> str:
    """The README's section: the sentences over all environments of the primary tests."""
    design = _results(analysis)
    rows = design.comparisons
    rows = rows.loc[(rows["scope"] == "all") & rows["test"].isin(PRIMARY_TESTS)]
    lines = "".join(f"- {sentence}\n" for sentence in rows["sentence"])
    return (
        "## Comparisons within participants\n\n"
        "Over all environments, each learner against the baseline within participants' "
        "blocks (`design.md` has every environment, the GEE model and the omnibus tests):\n\n"
        f"{lines}\n"
    )


def write_design_outputs(analysis: Analysis, folder: Path) -> None:
    design = _results(analysis)
    (folder / "design.md").write_text(design_markdown(analysis), encoding="utf-8")
    frames = {
        "design_comparisons.csv": design.comparisons,
        "design_omnibus.csv": design.omnibus,
        "survival_medians.csv": design.medians,
    }
    for name, frame in frames.items():
        frame.loc[:, list(DESIGN_FILES[name])].to_csv(folder / name, index=False)
    save_survival_curves(analysis, folder)


def _results(analysis: Analysis) -> DesignResults:
    if analysis.design is None:
        raise ValueError("the analysis has no design-respecting comparisons")
    return analysis.design


def _omnibus_table(omnibus: pd.DataFrame, analysis: Analysis) -> str:
    lines = [
        "| scope | threshold | blocks | Cochran's Q (df) | p | permutation p |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for _, row in omnibus.iterrows():
        scope = "all" if row["scope"] == "all" else environment_display(str(row["scope"]))
        q = "N/A" if pd.isna(row["cochran_q"]) else f"{row['cochran_q']:.2f} ({int(row['df'])})"
        lines.append(
            f"| {scope} | {threshold_label(float(row['threshold']))}% | "
            f"{_cell(row['blocks'], 'd')} | {q} | {_cell(row['p_value'], '.3f')} | "
            f"{_cell(row['p_permutation'], '.4f')} |"
        )
    learners = ", ".join(learner_display(name) for name in analysis.learners)
    return "\n".join(lines) + f"\n\nLearners: {learners}; blocks with a session of each."


def _median_table(medians: pd.DataFrame, analysis: Analysis) -> str:
    lines = [
        "| scope | measure | threshold | learner | reached / sessions | median (95% CI) |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for _, row in medians.iterrows():
        scope = "all" if row["scope"] == "all" else environment_display(str(row["scope"]))
        high = "open" if pd.isna(row["median_high"]) else f"{row['median_high']:g}"
        low = "N/A" if pd.isna(row["median_low"]) else f"{row['median_low']:g}"
        median = "N/A" if pd.isna(row["median"]) else f"{row['median']:g} ({low} to {high})"
        lines.append(
            f"| {scope} | {row['measure']} | {threshold_label(float(row['threshold']))}% | "
            f"{learner_display(str(row['learner']))} | {row['reached']} / {row['sessions']} | "
            f"{median} |"
        )
    return "\n".join(lines)


def _cell(value: object, spec: str) -> str:
    if value is None or pd.isna(value):  # type: ignore[call-overload]
        return "N/A"
    number = float(value)  # type: ignore[arg-type]
    return format(int(number) if spec == "d" else number, spec)
