"""Table 1 and the appendix p-value tables, in Markdown and in LaTeX (booktabs).

The forms follow the paper: Table 1 lists, per environment and learner, the total sessions
and per threshold the successful sessions and the mean episodes and actions required, with
``*`` (significantly worse than the baseline) and ``†`` (still so after the
Benjamini-Yekutieli correction); the appendix tables list the p-values of the comparisons
across all environments and of the environment-specific ones.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

from analysis.names import environment_display, learner_display, threshold_label
from analysis.results import Analysis
from analysis.stats import ALPHA, MEASURES, reached_column, required_column

MEASURE_NAMES = {
    "success": "Success Rate",
    "episodes": "Episodes Required",
    "actions": "Actions Required",
}
NOT_AVAILABLE = "N/A"


def format_mean(value: object) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return NOT_AVAILABLE
    return f"{float(value):.1f}"  # type: ignore[arg-type]


def format_p(value: object, latex: bool = False) -> str:
    """Four significant digits, in scientific notation below 0.001."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return NOT_AVAILABLE
    p = float(value)  # type: ignore[arg-type]
    if p == 0.0:  # below the smallest double SciPy can return
        return "$<$ 1e-300" if latex else "< 1e-300"
    if p >= 1e-3:
        return f"{p:.4g}"
    return f"{p:.3e}"


def _percent(fraction: float) -> str:
    return f"{threshold_label(fraction)}%"


# --- Markdown -------------------------------------------------------------------------------


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]], align: str) -> str:
    """A pipe table padded to aligned columns; ``align`` has one ``l`` or ``r`` per column."""
    widths = [max(3, len(header[i]), *(len(row[i]) for row in rows)) for i in range(len(header))]

    def line(cells: Sequence[str]) -> str:
        padded = [
            cell.ljust(width) if a == "l" else cell.rjust(width)
            for cell, width, a in zip(cells, widths, align, strict=True)
        ]
        return "| " + " | ".join(padded) + " |"

    rule = [
        ":" + "-" * (width - 1) if a == "l" else "-" * (width - 1) + ":"
        for width, a in zip(widths, align, strict=True)
    ]
    return "\n".join([line(header), "| " + " | ".join(rule) + " |", *(line(r) for r in rows)])


def _marked(text: str, star: bool, dagger: bool, latex: bool) -> str:
    if latex:
        return text + ("$^{*}$" if star else "") + ("$^{\\dagger}$" if dagger else "")
    return text + ("*" if star else "") + ("†" if dagger else "")


def _table1_cells(analysis: Analysis, row: dict[str, object], latex: bool) -> list[str]:
    """The cells of one learner's row of Table 1 after its name."""
    environment = str(row["environment"])
    learner = str(row["learner"])
    cells = [str(row["sessions"])]
    columns: list[tuple[str, float, str]] = []
    for measure in MEASURES:
        for threshold in analysis.thresholds:
            if measure == "success":
                text = str(row[reached_column(threshold)])
            else:
                text = format_mean(row[required_column(measure, threshold)])
            columns.append((measure, threshold, text))
    for measure, threshold, text in columns:
        star, dagger = (
            (False, False)
            if learner == analysis.baseline
            else analysis.marks(environment, measure, threshold, learner)
        )
        cells.append(_marked(text, star, dagger, latex))
    return cells


def _marks_used(analysis: Analysis) -> tuple[bool, bool, bool]:
    """Whether any cell of Table 1 carries ``*``, ``†`` or N/A (the legend defines only those)."""
    star = dagger = not_available = False
    for row in analysis.table1.to_dict("records"):
        learner = str(row["learner"])
        for measure in MEASURES:
            for threshold in analysis.thresholds:
                if measure != "success":
                    value = row[required_column(measure, threshold)]
                    not_available |= format_mean(value) == NOT_AVAILABLE
                if learner != analysis.baseline:
                    marked = analysis.marks(str(row["environment"]), measure, threshold, learner)
                    star |= marked[0]
                    dagger |= marked[1]
    return star, dagger, not_available


def _legend(analysis: Analysis, latex: bool) -> str:
    """The marks of Table 1 that its cells use; without any significant difference it says so."""
    star_used, dagger_used, not_available = _marks_used(analysis)
    baseline = learner_display(analysis.baseline)
    le = "$\\leq$" if latex else "≤"
    dash = "--" if latex else "–"
    star = "(*)" if latex else "*"
    dagger = "($\\dagger$)" if latex else "†"
    percent = "\\%" if latex else "%"
    fdr = f"{threshold_label(analysis.fdr)}{percent}"
    tests = (
        f"p {le} {ALPHA:g}; Fisher's exact test for the successful sessions, Welch's t-test "
        "for the episodes and actions required, over the sessions that reached the threshold"
    )
    parts = []
    if star_used:
        significant = f"{star} significantly worse than {baseline} ({tests})"
        if dagger_used:
            significant += (
                f"; {dagger} still significant after a Benjamini{dash}Yekutieli correction "
                f"over all {analysis.environment_tests} environment-specific comparisons at a "
                f"false discovery rate of {fdr}"
            )
        parts.append(significant + ".")
    else:
        parts.append(f"No learner is significantly worse than {baseline} ({tests}).")
    if not_available:
        parts.append(f"{NOT_AVAILABLE}: no session reached the threshold.")
    return " ".join(parts)


def table1_markdown(analysis: Analysis) -> str:
    thresholds = analysis.thresholds
    header = ["", "Total Sessions"]
    for measure in ("Successful", "Episodes Required", "Actions Required"):
        header += [f"{measure} {_percent(t)}" for t in thresholds]
    rows: list[list[str]] = []
    for environment in analysis.environments:
        rows.append([f"**{environment_display(environment)}**"] + [""] * (len(header) - 1))
        for row in analysis.table1.loc[analysis.table1["environment"] == environment].to_dict(
            "records"
        ):
            rows.append(
                [learner_display(str(row["learner"])), *_table1_cells(analysis, row, False)]
            )
    table = markdown_table(header, rows, "l" + "r" * (len(header) - 1))
    notes = "".join(f"\n- {note}" for note in analysis.notes)
    return f"{table}\n\nMarks: {_legend(analysis, latex=False)}\n{notes}".rstrip() + "\n"


def _p_cells(
    analysis: Analysis, scope: str, measure: str, threshold: float, latex: bool = False
) -> list[str]:
    cells = []
    for alternative in analysis.alternatives:
        row = analysis.comparison(scope, measure, threshold, alternative)
        cells.append(NOT_AVAILABLE if row is None else format_p(row["p_value"], latex))
    return cells


ALL_CAPTION = (
    "P-values for comparisons done across all environments. For the numbers of episodes and "
    "actions required, a type II ANOVA of an ordinary least squares model with factors for "
    "the learner, the environment and the position of the session in the participant's "
    "sequence, over the sessions of {baseline} and the alternative that reached the "
    "threshold (the learner factor's p-value). For the success rates, Fisher's exact test "
    "on the counts pooled over all environments."
)
RAW_CAPTION = (
    "Raw p-values for the environment-specific comparisons against {baseline}. Fisher's exact "
    "test for the success rates; Welch's unpaired t-test for the numbers of episodes and "
    "actions required, over the sessions that reached the threshold."
)
NA_EXPLAINED = "N/A: the test could not be done; comparisons.csv gives the reason."


def appendix_all_markdown(analysis: Analysis) -> str:
    header = ["Performance Measure", "Threshold"]
    header += [learner_display(a) for a in analysis.alternatives]
    rows = []
    for measure in MEASURES:
        for i, threshold in enumerate(analysis.thresholds):
            rows.append(
                [
                    MEASURE_NAMES[measure] if i == 0 else "",
                    _percent(threshold),
                    *_p_cells(analysis, "all", measure, threshold),
                ]
            )
    caption = ALL_CAPTION.format(baseline=learner_display(analysis.baseline))
    table = markdown_table(header, rows, "ll" + "r" * len(analysis.alternatives))
    return f"{table}\n\n{caption} {NA_EXPLAINED}\n"


def appendix_raw_markdown(analysis: Analysis) -> str:
    header = ["Environment", "Performance Measure", "Threshold"]
    header += [learner_display(a) for a in analysis.alternatives]
    rows = []
    for environment in analysis.environments:
        first_of_environment = True
        for measure in MEASURES:
            for i, threshold in enumerate(analysis.thresholds):
                rows.append(
                    [
                        environment_display(environment) if first_of_environment else "",
                        MEASURE_NAMES[measure] if i == 0 else "",
                        _percent(threshold),
                        *_p_cells(analysis, environment, measure, threshold),
                    ]
                )
                first_of_environment = False
    caption = RAW_CAPTION.format(baseline=learner_display(analysis.baseline))
    table = markdown_table(header, rows, "lll" + "r" * len(analysis.alternatives))
    return f"{table}\n\n{caption} {NA_EXPLAINED}\n"


# --- LaTeX ----------------------------------------------------------------------------------

_TEX_SPECIAL = {
    "\\": "\\textbackslash{}",
    "&": "\\&",
    "%": "\\%",
    "$": "\\$",
    "#": "\\#",
    "_": "\\_",
    "{": "\\{",
    "}": "\\}",
    "~": "\\textasciitilde{}",
    "^": "\\textasciicircum{}",
}


def tex_escape(text: str) -> str:
    escaped = "".join(_TEX_SPECIAL.get(character, character) for character in text)
    return escaped.replace("--", "-{}-")  # keep "--" from becoming a dash


def _tex_percent(fraction: float) -> str:
    return f"{threshold_label(fraction)}\\%"


def _and(items: Iterable[str]) -> str:
    """ "a", "a and b", "a, b and c"."""
    items = list(items)
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1]


def _tex_row(cells: Sequence[str]) -> str:
    return "    " + " & ".join(cells) + " \\\\"


def _tex_table(
    caption: str, label: str, spec: str, body: list[str], size: str | None = None
) -> str:
    lines = [
        "% Needs \\usepackage{booktabs} in the preamble.",
        "\\begin{table*}[t]",
        "  \\centering",
        f"  \\caption{{{caption}}}",
        f"  \\label{{{label}}}",
    ]
    if size:
        lines.append(f"  {{\\{size}")
    lines += [f"  \\begin{{tabular}}{{{spec}}}", "    \\toprule", *body, "    \\bottomrule"]
    lines.append("  \\end{tabular}" + ("}" if size else ""))
    lines.append("\\end{table*}")
    return "\n".join(lines) + "\n"


def table1_latex(analysis: Analysis) -> str:
    thresholds = analysis.thresholds
    k = len(thresholds)
    columns = 2 + 3 * k
    groups = ["", ""]
    rules = []
    for g, name in enumerate(("Successful", "Episodes Required", "Actions Required")):
        groups.append(f"\\multicolumn{{{k}}}{{c}}{{{name}}}")
        first = 3 + g * k
        rules.append(f"\\cmidrule(lr){{{first}-{first + k - 1}}}")
    body = [_tex_row(groups), "    " + " ".join(rules)]
    body.append(_tex_row(["", "Total Sessions", *([_tex_percent(t) for t in thresholds] * 3)]))
    for environment in analysis.environments:
        body.append("    \\midrule")
        name = tex_escape(environment_display(environment))
        body.append(f"    \\multicolumn{{{columns}}}{{l}}{{\\textbf{{{name}}}}} \\\\")
        for row in analysis.table1.loc[analysis.table1["environment"] == environment].to_dict(
            "records"
        ):
            body.append(
                _tex_row(
                    [
                        tex_escape(learner_display(str(row["learner"]))),
                        *_table1_cells(analysis, row, True),
                    ]
                )
            )
    caption = (
        "Results of the user study. Learning sessions were evaluated on whether the agent's "
        "policies reached "
        + _and(_tex_percent(t) for t in thresholds)
        + " of the optimal total return, and on the number of episodes and the number of "
        "actions (under either the teacher's or the agent's control) required on average to "
        "reach these thresholds. " + _legend(analysis, latex=True)
    )
    for note in analysis.notes:
        caption += " " + tex_escape(note[0].upper() + note[1:]) + "."
    return _tex_table(caption, "tab:study_results", "l" + "r" * (columns - 1), body)


def appendix_all_latex(analysis: Analysis) -> str:
    header = ["Performance Measure", "Threshold"]
    header += [tex_escape(learner_display(a)) for a in analysis.alternatives]
    body = [_tex_row(header)]
    for measure in MEASURES:
        body.append("    \\midrule")
        for i, threshold in enumerate(analysis.thresholds):
            body.append(
                _tex_row(
                    [
                        MEASURE_NAMES[measure] if i == 0 else "",
                        _tex_percent(threshold),
                        *_p_cells(analysis, "all", measure, threshold, latex=True),
                    ]
                )
            )
    caption = tex_escape(ALL_CAPTION.format(baseline=learner_display(analysis.baseline)))
    caption += " " + tex_escape(NA_EXPLAINED)
    spec = "ll" + "r" * len(analysis.alternatives)
    return _tex_table(caption, "tab:analysis_all", spec, body)


def appendix_raw_latex(analysis: Analysis) -> str:
    header = ["Environment", "Performance Measure", "Threshold"]
    header += [tex_escape(learner_display(a)) for a in analysis.alternatives]
    body = [_tex_row(header)]
    for environment in analysis.environments:
        body.append("    \\midrule")
        first_of_environment = True
        for measure in MEASURES:
            for i, threshold in enumerate(analysis.thresholds):
                body.append(
                    _tex_row(
                        [
                            tex_escape(environment_display(environment))
                            if first_of_environment
                            else "",
                            MEASURE_NAMES[measure] if i == 0 else "",
                            _tex_percent(threshold),
                            *_p_cells(analysis, environment, measure, threshold, latex=True),
                        ]
                    )
                )
                first_of_environment = False
    caption = tex_escape(RAW_CAPTION.format(baseline=learner_display(analysis.baseline)))
    caption += " " + tex_escape(NA_EXPLAINED)
    spec = "lll" + "r" * len(analysis.alternatives)
    return _tex_table(caption, "tab:analysis_raw", spec, body, size="footnotesize")
