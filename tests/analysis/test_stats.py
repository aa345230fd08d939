"""Each statistic on hand-checkable data and on values published in the SciPy documentation
and in the paper."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from analysis.stats import (
    anova_learner,
    benjamini_yekutieli,
    compare,
    fisher_success,
    welch_t_test,
)

# --- Fisher's exact test --------------------------------------------------------------------


def test_fisher_matches_the_scipy_documentation_example() -> None:
    # scipy.stats.fisher_exact docs: fisher_exact([[8, 2], [1, 5]]) -> statistic 20.0,
    # pvalue 0.034965034965034975.
    result = fisher_success(8, 10, 1, 6)
    assert result.test == "fisher_exact"
    assert result.statistic == pytest.approx(20.0)
    assert result.p_value == pytest.approx(0.034965034965034975, rel=1e-12)


def test_fisher_by_hand_from_the_hypergeometric_distribution() -> None:
    # [[6, 2], [1, 4]]: rows 8 and 5, first column 7, n = 13. P(a) = C(8,a) C(5,7-a) / C(13,7)
    # for a = 2..7 is (28, 280, 700, 560, 140, 8) / 1716; the observed a = 6 has 140, and
    # the two-sided p sums the tables at most that likely: (28 + 140 + 8) / 1716.
    # (The brief quoted 0.2797 for this table; that is not its p-value.)
    result = fisher_success(6, 8, 1, 5)
    assert result.p_value == pytest.approx(176 / 1716, rel=1e-12)
    assert result.statistic == pytest.approx((6 * 4) / (2 * 1))


def test_fisher_tea_tasting() -> None:
    # Fisher's lady tasting tea, [[3, 1], [1, 3]]: (1 + 16 + 1) / 70 two-sided.
    assert fisher_success(3, 4, 1, 4).p_value == pytest.approx(34 / 70)


def test_fisher_needs_sessions_in_both_groups() -> None:
    result = fisher_success(0, 0, 3, 5)
    assert result.p_value is None
    assert "no baseline sessions" in result.note


# The paper's Table 1 counts and the raw p-values its appendix publishes for them (Fisher's
# exact test, success rates): (environment, sessions per learner, successes at 50% and 80%
# for BAM, model-based IRL, behavioural cloning).
PAPER_COUNTS = {
    "two-rooms": (27, (24, 14), (25, 6), (17, 1)),
    "doorway": (27, (19, 5), (18, 4), (12, 4)),
    "two-fields": (31, (27, 18), (27, 12), (10, 0)),
    "three-fields": (31, (24, 20), (22, 12), (17, 2)),
}
# Published values that follow from the published counts. Four others do not (two-fields
# 50% cloning, three-fields 50% both, three-fields 80% model-based: Fisher's test on the
# table's own counts gives 2.02e-05, 0.772, 0.106 and 0.0744, not the 4.31e-06, 1, 0.0620
# and 0.0413 printed), so the paper must have tested slightly different counts there.
PAPER_SUCCESS_P = {
    ("two-rooms", 0.5, "model-based"): 1.0,
    ("two-rooms", 0.5, "cloning"): 5.367713e-02,
    ("two-rooms", 0.8, "model-based"): 4.727039e-02,
    ("two-rooms", 0.8, "cloning"): 1.291742e-04,
    ("doorway", 0.5, "model-based"): 1.0,
    ("doorway", 0.5, "cloning"): 9.777568e-02,
    ("doorway", 0.8, "model-based"): 1.0,
    ("doorway", 0.8, "cloning"): 1.0,
    ("two-fields", 0.5, "model-based"): 1.0,
    ("two-fields", 0.8, "model-based"): 0.2035422,
    ("two-fields", 0.8, "cloning"): 2.230871e-07,
    ("three-fields", 0.8, "cloning"): 2.376083e-06,
}


def paper_summary() -> pd.DataFrame:
    """Sessions with the paper's success counts (no evaluations needed for success)."""
    rows = []
    for environment, (n, *per_learner) in PAPER_COUNTS.items():
        for learner, (s50, s80) in zip(("bam", "model-based", "cloning"), per_learner, strict=True):
            for i in range(n):
                rows.append(
                    {
                        "session_id": f"{environment}-{learner}-{i}",
                        "participant_id": f"p{i}",
                        "domain": "x",
                        "environment": environment,
                        "learner": learner,
                        "position": 0,
                        "completed": True,
                        "evaluations": 0,
                        "reached_50": i < s50,
                        "reached_80": i < s80,
                    }
                )
    frame = pd.DataFrame(rows)
    for column in ("episodes_50", "episodes_80", "actions_50", "actions_80"):
        frame[column] = pd.array([pd.NA] * len(frame), dtype="Int64")
    return frame


def test_success_comparisons_reproduce_the_papers_published_p_values() -> None:
    comparisons = compare(paper_summary(), (0.5, 0.8), "bam", 0.2)
    for (environment, threshold, alternative), published in PAPER_SUCCESS_P.items():
        row = comparisons.loc[
            (comparisons["scope"] == environment)
            & (comparisons["measure"] == "success")
            & (comparisons["threshold"] == threshold)
            & (comparisons["alternative"] == alternative)
        ].iloc[0]
        assert row["p_value"] == pytest.approx(published, rel=1e-6), (environment, threshold)
    # Two Rooms at 80%: BAM 14 of 27 against model-based IRL 6 of 27 is significant (the
    # paper's text: p = 0.047) and marked worse.
    row = comparisons.loc[
        (comparisons["scope"] == "two-rooms")
        & (comparisons["measure"] == "success")
        & (comparisons["threshold"] == 0.8)
        & (comparisons["alternative"] == "model-based")
    ].iloc[0]
    assert row["significant"] is True and row["worse"]
    assert (row["baseline_value"], row["alternative_value"]) == (14, 6)


# --- Welch's t-test -------------------------------------------------------------------------


def test_welch_with_one_degree_of_freedom_matches_the_cauchy_closed_form() -> None:
    # Baseline [1, 3]: mean 2, variance 2; alternative [4, 4]: mean 4, variance 0.
    # se = sqrt(2/2 + 0/2) = 1, t = (2 - 4) / 1 = -2; Welch-Satterthwaite
    # df = (2/2)^2 / ((2/2)^2 / 1) = 1, and with one degree of freedom t is Cauchy:
    # p = 1 - (2/pi) atan(|t|).
    result = welch_t_test([1, 3], [4, 4])
    assert result.statistic == pytest.approx(-2.0)
    assert result.p_value == pytest.approx(1 - 2 / math.pi * math.atan(2), rel=1e-12)


def test_welch_with_two_degrees_of_freedom_matches_the_closed_form() -> None:
    # Baseline [1, 2, 3]: mean 2, variance 1; alternative [5, 5]: variance 0.
    # se = sqrt(1/3), t = -3 / sqrt(1/3) = -sqrt(27), df = (1/3)^2 / ((1/3)^2 / 2) = 2,
    # and for 2 degrees of freedom p = 1 - |t| / sqrt(2 + t^2) = 1 - sqrt(27/29).
    result = welch_t_test([1, 2, 3], [5, 5])
    assert result.statistic == pytest.approx(-math.sqrt(27))
    assert result.p_value == pytest.approx(1 - math.sqrt(27 / 29), rel=1e-12)


def test_welch_from_the_formula_with_unequal_variances() -> None:
    from scipy.stats import t as t_distribution

    b = np.array([2.0, 2.0, 3.0, 3.0])
    a = np.array([6.0, 7.0, 9.0])
    vb, va = b.var(ddof=1) / len(b), a.var(ddof=1) / len(a)
    t = (b.mean() - a.mean()) / math.sqrt(vb + va)
    df = (vb + va) ** 2 / (vb**2 / (len(b) - 1) + va**2 / (len(a) - 1))
    result = welch_t_test(b, a)
    assert result.statistic == pytest.approx(t, rel=1e-12)
    assert result.p_value == pytest.approx(2 * t_distribution.sf(abs(t), df), rel=1e-10)
    # Not Student's pooled-variance test, whose p-value differs here.
    from scipy.stats import ttest_ind

    assert result.p_value != pytest.approx(ttest_ind(b, a).pvalue, rel=1e-3)


@pytest.mark.parametrize(
    ("baseline", "alternative", "reason"),
    [
        ([1.0], [2.0, 3.0], "1 baseline and 2 alternative"),
        ([1.0, 2.0], [], "2 baseline and 0 alternative"),
        ([3.0, 3.0], [5.0, 5.0, 5.0], "no variance in either group"),
    ],
)
def test_welch_gives_no_p_value_for_groups_too_small(baseline, alternative, reason) -> None:
    result = welch_t_test(baseline, alternative)
    assert result.p_value is None and result.statistic is None
    assert reason in result.note


# --- Benjamini-Yekutieli ---------------------------------------------------------------------

# scipy.stats.false_discovery_control docs: 15 p-values from Benjamini and Hochberg (1995)
# and their Benjamini-Hochberg adjustment.
DOCS_P = [0.0001, 0.0004, 0.0019, 0.0095, 0.0201, 0.0278, 0.0298, 0.0344, 0.0459, 0.3240]
DOCS_P += [0.4262, 0.5719, 0.6528, 0.7590, 1.000]
DOCS_BH = [0.0015, 0.003, 0.0095, 0.035625, 0.0603, 0.06385714, 0.06385714, 0.0645, 0.0765]
DOCS_BH += [0.486, 0.58118182, 0.714875, 0.75323077, 0.81321429, 1.0]


def test_by_is_the_documented_bh_adjustment_times_the_harmonic_sum() -> None:
    # Benjamini-Yekutieli multiplies the Benjamini-Hochberg adjustment by
    # c(m) = 1 + 1/2 + ... + 1/m (both take the running minimum from the largest p down,
    # which commutes with a constant factor), capped at 1.
    c = sum(1 / i for i in range(1, len(DOCS_P) + 1))
    expected = np.minimum(1.0, np.array(DOCS_BH) * c)
    assert benjamini_yekutieli(DOCS_P) == pytest.approx(expected, rel=1e-6)


def test_by_by_hand_and_in_the_input_order() -> None:
    # The docs' unsorted example [0.5, 0.6, 0.1, 0.001] has BH [0.6, 0.6, 0.2, 0.004];
    # c(4) = 25/12.
    adjusted = benjamini_yekutieli([0.5, 0.6, 0.1, 0.001])
    assert adjusted == pytest.approx([1.0, 1.0, 0.2 * 25 / 12, 0.004 * 25 / 12])
    assert benjamini_yekutieli([]).size == 0


# --- The ANOVA across environments -----------------------------------------------------------


def balanced_frame() -> pd.DataFrame:
    # A 2 x 2 x 2 design (learner x environment x position), one session per cell.
    rows = [
        ("bam", "e1", 0, 1.0),
        ("bam", "e1", 1, 3.0),
        ("bam", "e2", 0, 4.0),
        ("bam", "e2", 1, 6.0),
        ("cloning", "e1", 0, 5.0),
        ("cloning", "e1", 1, 5.0),
        ("cloning", "e2", 0, 8.0),
        ("cloning", "e2", 1, 10.0),
    ]
    return pd.DataFrame(rows, columns=["learner", "environment", "position", "value"])


def test_anova_by_hand_on_a_balanced_design() -> None:
    # Grand mean 42/8 = 5.25. Learner means 3.5 and 7, environment means 3.5 and 7,
    # position means 4.5 and 6; in a balanced two-level design each factor's sum of squares
    # is 8 * (difference / 2)^2: 24.5, 24.5 and 4.5. The total sum of squares is 55.5, so
    # the additive model leaves 55.5 - 24.5 - 24.5 - 4.5 = 2 on 8 - 4 = 4 degrees of freedom,
    # and F(learner) = 24.5 / (2 / 4) = 49. With one numerator degree of freedom F = t^2 for
    # t with 4 degrees of freedom, whose two-sided p is 1 - u (3 - u^2) / 2,
    # u = t / sqrt(t^2 + 4).
    result = anova_learner(balanced_frame(), ("bam", "cloning"))
    assert result.test == "anova_type2"
    assert result.statistic == pytest.approx(49.0)
    u = 7 / math.sqrt(49 + 4)
    assert result.p_value == pytest.approx(1 - u * (3 - u * u) / 2, rel=1e-9)
    assert "factors: learner, environment, position" in result.note


def _nested_f(frame: pd.DataFrame) -> tuple[float, int, int]:
    """The learner's F from two least-squares fits (with and without the learner), by
    NumPy alone: ((RSS_reduced - RSS_full) / df) / (RSS_full / df_residual)."""

    def dummies(column: str) -> np.ndarray:
        levels = sorted(frame[column].unique())
        return np.column_stack([(frame[column] == level).to_numpy(float) for level in levels[1:]])

    y = frame["value"].to_numpy(float)
    intercept = np.ones((len(frame), 1))
    nuisance = np.hstack([intercept, dummies("environment"), dummies("position")])
    full = np.hstack([nuisance, dummies("learner")])

    def rss(x: np.ndarray) -> tuple[float, int]:
        beta, *_ = np.linalg.lstsq(x, y, rcond=None)
        return float(np.sum((y - x @ beta) ** 2)), int(np.linalg.matrix_rank(x))

    rss_full, rank_full = rss(full)
    rss_reduced, rank_reduced = rss(nuisance)
    df = rank_full - rank_reduced
    df_residual = len(y) - rank_full
    return ((rss_reduced - rss_full) / df) / (rss_full / df_residual), df, df_residual


def test_anova_in_the_studys_design_where_environment_and_position_overlap() -> None:
    from scipy.stats import f as f_distribution

    # The paper's protocol: each environment is taught at fixed positions (Two Rooms and Two
    # Fields at 0-2, Doorway and Three Fields at 3-5), so the environment and position
    # dummies are linearly dependent. The learner's type II test must still equal the
    # comparison of the models with and without the learner.
    rng = np.random.default_rng(7)
    rows = []
    for participant in range(12):
        first, second = (
            ("two-rooms", "doorway") if participant % 2 == 0 else ("two-fields", "three-fields")
        )
        for offset, environment in ((0, first), (3, second)):
            learners = ["bam", "cloning", "model-based"]
            rng.shuffle(learners)
            for slot, learner in enumerate(learners):
                effect = {"bam": 2.0, "cloning": 5.0, "model-based": 3.0}[learner]
                rows.append(
                    (learner, environment, offset + slot, effect + offset * 0.3 + rng.normal())
                )
    frame = pd.DataFrame(rows, columns=["learner", "environment", "position", "value"])
    frame = frame.loc[frame["learner"] != "model-based"].reset_index(drop=True)
    f_value, df, df_residual = _nested_f(frame)
    assert df == 1
    result = anova_learner(frame, ("bam", "cloning"))
    assert "environment and position overlap (rank-deficient design)" in result.note
    assert result.statistic == pytest.approx(f_value, rel=1e-9)
    assert result.p_value == pytest.approx(f_distribution.sf(f_value, df, df_residual), rel=1e-9)


def test_anova_with_one_learner_varying_only_is_the_pooled_t_test_squared() -> None:
    from scipy.stats import ttest_ind

    frame = pd.DataFrame(
        {
            "learner": ["bam"] * 4 + ["cloning"] * 3,
            "environment": ["two-rooms"] * 7,
            "position": [2] * 7,
            "value": [2.0, 3.0, 3.0, 5.0, 6.0, 8.0, 7.0],
        }
    )
    result = anova_learner(frame, ("bam", "cloning"))
    pooled = ttest_ind(frame["value"][:4], frame["value"][4:], equal_var=True)
    assert result.statistic == pytest.approx(pooled.statistic**2)
    assert result.p_value == pytest.approx(pooled.pvalue)
    assert (
        "left out factor environment (one level: two-rooms), factor position (one level: 2)"
        in result.note
    )


@pytest.mark.parametrize(
    ("frame", "reason"),
    [
        (
            pd.DataFrame(
                {
                    "learner": ["bam", "bam", "bam", "cloning"],
                    "environment": ["e1", "e2", "e1", "e2"],
                    "position": [0, 1, 2, 0],
                    "value": [1.0, 2.0, 3.0, 4.0],
                }
            ),
            "too few sessions for an ANOVA: 3 BAM and 1 Behavioral Cloning",
        ),
        (
            # Every BAM session at position 0 and every cloning session at position 1: the
            # learner cannot be told apart from the position.
            pd.DataFrame(
                {
                    "learner": ["bam", "bam", "cloning", "cloning", "bam", "cloning"],
                    "environment": ["e1", "e2", "e1", "e2", "e1", "e2"],
                    "position": [0, 0, 1, 1, 0, 1],
                    "value": [1.0, 2.0, 3.0, 5.0, 1.5, 4.0],
                }
            ),
            "the learner is confounded with the other factors",
        ),
        (
            # Four sessions, four parameters: nothing left to estimate the error.
            pd.DataFrame(
                {
                    "learner": ["bam", "bam", "cloning", "cloning"],
                    "environment": ["e1", "e2", "e1", "e2"],
                    "position": [0, 1, 1, 2],
                    "value": [1.0, 2.0, 3.0, 5.0],
                }
            ),
            "no residual degrees of freedom",
        ),
        (
            # Exactly additive values: nothing left for the error term.
            pd.DataFrame(
                {
                    "learner": ["bam"] * 4 + ["cloning"] * 4,
                    "environment": ["e1", "e1", "e2", "e2"] * 2,
                    "position": [0] * 8,
                    "value": [1.0, 1.0, 3.0, 3.0, 2.0, 2.0, 4.0, 4.0],
                }
            ),
            "the model fits exactly, no residual variance",
        ),
        (
            # Every value equal.
            pd.DataFrame(
                {
                    "learner": ["bam", "bam", "cloning", "cloning", "bam"],
                    "environment": ["e1", "e2", "e1", "e2", "e1"],
                    "position": [0, 1, 1, 0, 0],
                    "value": [2.0] * 5,
                }
            ),
            "the model fits exactly, no residual variance",
        ),
    ],
)
def test_anova_gives_no_p_value_when_it_cannot_be_done(frame, reason) -> None:
    result = anova_learner(frame, ("bam", "cloning"))
    assert result.p_value is None and result.statistic is None
    assert reason in result.note


# --- Comparisons where a learner is missing --------------------------------------------------


def test_comparisons_say_why_when_a_learner_was_not_taught(tmp_path) -> None:
    from analysis.data import load_tables
    from analysis.stats import session_measures

    from .conftest import curve, write_export

    sessions = [
        # Two Rooms: BAM and behavioural cloning, 3 sessions each.
        *[("r" + str(i), f"p{i}", "two-rooms", "bam", 0, curve(2 + i % 2, 4, 6)) for i in range(3)],
        *[
            ("c" + str(i), f"p{i}", "two-rooms", "cloning", 1, curve(5 + i, None, 9))
            for i in range(3)
        ],
        # Doorway: behavioural cloning only.
        *[("d" + str(i), f"p{i}", "doorway", "cloning", 2, curve(3, 5, 6)) for i in range(3)],
        # Wall: BAM and model-based IRL, the latter never reaching 50%.
        *[("w" + str(i), f"p{i}", "wall", "bam", 0, curve(2, 3, 4)) for i in range(2)],
        *[
            ("m" + str(i), f"p{i}", "wall", "model-based", 1, curve(None, None, 4))
            for i in range(2)
        ],
    ]
    loaded, evaluations = load_tables(write_export(tmp_path / "export", sessions))
    comparisons = compare(session_measures(loaded, evaluations, (0.5,)), (0.5,), "bam", 0.2)
    notes = {
        (r["scope"], r["measure"], r["alternative"]): (r["test"], r["note"])
        for r in comparisons.to_dict("records")
    }
    assert notes[("doorway", "success", "cloning")] == ("N/A", "no BAM sessions in Doorway")
    assert notes[("two-rooms", "episodes", "model-based")] == (
        "N/A",
        "no Model-Based IRL sessions in Two Rooms",
    )
    assert notes[("wall", "episodes", "model-based")] == (
        "N/A",
        "too few sessions for a t-test: 2 BAM and 0 Model-Based IRL sessions in Wall reached "
        "50% (needs at least 2 in each)",
    )
    # Across environments, cloning is compared where both were taught (Two Rooms), not in
    # Doorway, where it was taught alone: 3 of 3 against 3 of 3.
    test, note = notes[("all", "success", "cloning")]
    assert test == "fisher_exact"
    assert note == (
        "3 of 3 vs 3 of 3 sessions reached 50%; left out Doorway, Wall (not both learners "
        "taught there); no difference"
    )
    # Only the tests that were done enter the correction, and they all get an adjusted p.
    scoped = comparisons.loc[comparisons["scope"] != "all"]
    assert scoped["p_adjusted"].notna().tolist() == scoped["p_value"].notna().tolist()
