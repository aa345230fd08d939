"""Table 1 and the appendix tables rendered from the fixed small study (conftest.small_study),
compared against their full expected text.

The numbers can be checked by hand from conftest's plan. Two Rooms, BAM reaches 50% after
2, 2, 3 and 3 episodes (mean 2.5) with 24, 24, 39 and 39 actions (10 per episode plus the
episode number squared: mean 31.5). Model-based IRL needs 3, 4, 4, 5 episodes (4.0; Welch
t = -3, p = 0.027: *). Behavioural cloning reaches 80% in no session: N/A, and 0 of 4
against BAM's 4 of 4 is Fisher p = 2/70 = 0.029 (*). In Doorway, cloning needs 7, 7, 8
episodes against BAM's 2, 3, 3, 4 (p = 4.3e-4) and one of its sessions has no evaluations.
With 18 environment-specific p-values, Benjamini-Yekutieli multiplies the smallest by
18 * (1 + 1/2 + ... + 1/18) = 62.9: 0.027 and, for the second, 0.030 (both daggers), while
the third smallest (0.0149) becomes 0.30 > 0.2.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from analysis.data import load_tables
from analysis.results import Analysis, analyze
from analysis.tables import (
    appendix_all_markdown,
    appendix_raw_markdown,
    format_p,
    table1_latex,
    table1_markdown,
)


@pytest.fixture
def analysis(export: Path) -> Analysis:
    notes: list[str] = []
    sessions, evaluations = load_tables(export, notes=notes)
    return analyze(sessions, evaluations, notes=notes)


TABLE1_MD = """\
|                    | Total Sessions | Successful 50% | Successful 80% | Episodes Required 50% | Episodes Required 80% | Actions Required 50% | Actions Required 80% |
| :----------------- | -------------: | -------------: | -------------: | --------------------: | --------------------: | -------------------: | -------------------: |
| **Two Rooms**      |                |                |                |                       |                       |                      |                      |
| BAM                |              4 |              4 |              4 |                   2.5 |                   3.5 |                 31.5 |                 47.5 |
| Model-Based IRL    |              4 |              4 |              2 |                  4.0* |                  6.5* |                56.5* |                107.5 |
| Behavioral Cloning |              4 |              2 |             0* |                  8.5* |                   N/A |               157.5* |                  N/A |
| **Doorway**        |                |                |                |                       |                       |                      |                      |
| BAM                |              4 |              4 |              4 |                   3.0 |                   5.0 |                 39.5 |                 75.5 |
| Model-Based IRL    |              4 |              4 |              1 |                   3.0 |                   5.0 |                 39.5 |                 75.0 |
| Behavioral Cloning |              4 |              3 |             0* |                 7.3*† |                   N/A |              127.3*† |                  N/A |

Marks: * significantly worse than BAM (p ≤ 0.05; Fisher's exact test for the successful sessions, Welch's t-test for the episodes and actions required, over the sessions that reached the threshold); † still significant after a Benjamini–Yekutieli correction over all 18 environment-specific comparisons at a false discovery rate of 20%. N/A: no session reached the threshold.

- 1 learning session had no evaluations; it counts in the total sessions and reached no threshold
"""

TABLE1_TEX = r"""% Needs \usepackage{booktabs} in the preamble.
\begin{table*}[t]
  \centering
  \caption{Results of the user study. Learning sessions were evaluated on whether the agent's policies reached 50\% and 80\% of the optimal total return, and on the number of episodes and the number of actions (under either the teacher's or the agent's control) required on average to reach these thresholds. (*) significantly worse than BAM (p $\leq$ 0.05; Fisher's exact test for the successful sessions, Welch's t-test for the episodes and actions required, over the sessions that reached the threshold); ($\dagger$) still significant after a Benjamini--Yekutieli correction over all 18 environment-specific comparisons at a false discovery rate of 20\%. N/A: no session reached the threshold. 1 learning session had no evaluations; it counts in the total sessions and reached no threshold.}
  \label{tab:study_results}
  \begin{tabular}{lrrrrrrr}
    \toprule
     &  & \multicolumn{2}{c}{Successful} & \multicolumn{2}{c}{Episodes Required} & \multicolumn{2}{c}{Actions Required} \\
    \cmidrule(lr){3-4} \cmidrule(lr){5-6} \cmidrule(lr){7-8}
     & Total Sessions & 50\% & 80\% & 50\% & 80\% & 50\% & 80\% \\
    \midrule
    \multicolumn{8}{l}{\textbf{Two Rooms}} \\
    BAM & 4 & 4 & 4 & 2.5 & 3.5 & 31.5 & 47.5 \\
    Model-Based IRL & 4 & 4 & 2 & 4.0$^{*}$ & 6.5$^{*}$ & 56.5$^{*}$ & 107.5 \\
    Behavioral Cloning & 4 & 2 & 0$^{*}$ & 8.5$^{*}$ & N/A & 157.5$^{*}$ & N/A \\
    \midrule
    \multicolumn{8}{l}{\textbf{Doorway}} \\
    BAM & 4 & 4 & 4 & 3.0 & 5.0 & 39.5 & 75.5 \\
    Model-Based IRL & 4 & 4 & 1 & 3.0 & 5.0 & 39.5 & 75.0 \\
    Behavioral Cloning & 4 & 3 & 0$^{*}$ & 7.3$^{*}$$^{\dagger}$ & N/A & 127.3$^{*}$$^{\dagger}$ & N/A \\
    \bottomrule
  \end{tabular}
\end{table*}
"""

APPENDIX_ALL_MD = """\
| Performance Measure | Threshold | Model-Based IRL | Behavioral Cloning |
| :------------------ | :-------- | --------------: | -----------------: |
| Success Rate        | 50%       |               1 |                0.2 |
|                     | 80%       |         0.02564 |          1.554e-04 |
| Episodes Required   | 50%       |          0.1428 |          8.095e-05 |
|                     | 80%       |          0.1027 |                N/A |
| Actions Required    | 50%       |          0.1404 |          5.922e-05 |
|                     | 80%       |         0.09938 |                N/A |

P-values for comparisons done across all environments. For the numbers of episodes and actions required, a type II ANOVA of an ordinary least squares model with factors for the learner, the environment and the position of the session in the participant's sequence, over the sessions of BAM and the alternative that reached the threshold (the learner factor's p-value). For the success rates, Fisher's exact test on the counts pooled over all environments. N/A: the test could not be done; comparisons.csv gives the reason.
"""

APPENDIX_RAW_MD = """\
| Environment | Performance Measure | Threshold | Model-Based IRL | Behavioral Cloning |
| :---------- | :------------------ | :-------- | --------------: | -----------------: |
| Two Rooms   | Success Rate        | 50%       |               1 |             0.4286 |
|             |                     | 80%       |          0.4286 |            0.02857 |
|             | Episodes Required   | 50%       |         0.02734 |            0.01506 |
|             |                     | 80%       |           0.048 |                N/A |
|             | Actions Required    | 50%       |         0.03382 |            0.04733 |
|             |                     | 80%       |         0.07967 |                N/A |
| Doorway     | Success Rate        | 50%       |               1 |                  1 |
|             |                     | 80%       |          0.1429 |            0.02857 |
|             | Episodes Required   | 50%       |               1 |          4.335e-04 |
|             |                     | 80%       |             N/A |                N/A |
|             | Actions Required    | 50%       |               1 |          9.652e-04 |
|             |                     | 80%       |             N/A |                N/A |

Raw p-values for the environment-specific comparisons against BAM. Fisher's exact test for the success rates; Welch's unpaired t-test for the numbers of episodes and actions required, over the sessions that reached the threshold. N/A: the test could not be done; comparisons.csv gives the reason.
"""


def test_table1_markdown(analysis: Analysis) -> None:
    assert table1_markdown(analysis) == TABLE1_MD


def test_table1_latex(analysis: Analysis) -> None:
    assert table1_latex(analysis) == TABLE1_TEX


def test_appendix_all_markdown(analysis: Analysis) -> None:
    assert appendix_all_markdown(analysis) == APPENDIX_ALL_MD


def test_appendix_raw_markdown(analysis: Analysis) -> None:
    assert appendix_raw_markdown(analysis) == APPENDIX_RAW_MD


@pytest.mark.parametrize(
    ("p", "text"),
    [
        (1.0, "1"),
        (0.42857142857142855, "0.4286"),
        (0.001, "0.001"),
        (0.00043346554369481607, "4.335e-04"),
        (2.2e-16, "2.200e-16"),
        (0.0, "< 1e-300"),
        (None, "N/A"),
        (float("nan"), "N/A"),
    ],
)
def test_p_values_are_formatted_like_the_papers_tables(p, text) -> None:
    assert format_p(p) == text


def test_another_baseline_comes_first_and_is_the_one_compared_with(export: Path) -> None:
    sessions, evaluations = load_tables(export)
    analysis = analyze(sessions, evaluations, baseline="model-based", thresholds=(0.6,))
    lines = table1_markdown(analysis).splitlines()
    assert lines[0].split("|")[2:-1] == [
        " Total Sessions ",
        " Successful 60% ",
        " Episodes Required 60% ",
        " Actions Required 60% ",
    ]
    assert [line.split("|")[1].strip() for line in lines[2:6]] == [
        "**Two Rooms**",
        "Model-Based IRL",
        "BAM",
        "Behavioral Cloning",
    ]
    assert "significantly worse than Model-Based IRL" in table1_markdown(analysis)
    assert set(analysis.comparisons["baseline"]) == {"model-based"}
    assert set(analysis.comparisons["alternative"]) == {"bam", "cloning"}


def test_the_legend_defines_only_the_marks_the_table_uses(export: Path) -> None:
    """At a false discovery rate of 0.1% no difference survives the correction: no cell has a
    dagger, so neither legend defines one. At the 50% threshold alone no cell is N/A. Against
    cloning as the baseline no learner is worse: no star, and the legend says so."""
    sessions, evaluations = load_tables(export)
    strict = analyze(sessions, evaluations, fdr=0.001)
    text = table1_markdown(strict)
    table, legend = text.split("\n\nMarks: ")
    assert "*" in table and "†" not in table
    assert legend.startswith("* significantly worse than BAM")
    assert "†" not in legend and "Benjamini" not in legend
    assert "\\dagger" not in table1_latex(strict)
    # At the 50% threshold alone every cell has a number: no N/A, and its definition goes too.
    only_half = analyze(sessions, evaluations, thresholds=(0.5,))
    table, legend = table1_markdown(only_half).split("\n\nMarks: ")
    assert "N/A" not in table and "N/A" not in legend
    better = analyze(sessions, evaluations, baseline="cloning")
    table, legend = table1_markdown(better).split("\n\nMarks: ")
    assert "*" not in table.replace("**", "")
    assert legend.startswith("No learner is significantly worse than Behavioral Cloning (p ≤ 0.05")
    assert "†" not in legend
