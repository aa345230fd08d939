"""Our ANOVA and Welch's t-test on worked examples published with statsmodels and SciPy,
compared with the numbers printed there.

``anova_learner`` fits only the additive model ``value ~ C(learner) + C(environment) +
C(position)`` (a factor with one level left out) and reports the learner's type II F and p.
The published examples used here fit that same model; the better-known ones with an
interaction term (the Moore example in the ``anova_lm`` docstring, the kidney type I/II/III
tables) fit a different model and cannot be reproduced by our function, so they are not used.
Our result carries F and p only: the published sums of squares and degrees of freedom are
checked through them (F times the published residual mean square gives the learner's sum of
squares; p is the F distribution's tail at the published degrees of freedom).
"""

from __future__ import annotations

from collections.abc import Sequence
from decimal import Decimal

import numpy as np
import pandas as pd
import pytest
from scipy.stats import f as f_distribution
from scipy.stats import norm

from analysis.stats import anova_learner, welch_t_test

LEARNERS = ("bam", "cloning")


def printed(text: str) -> object:
    """``text`` as printed, to within half a unit in its last printed digit."""
    exponent = Decimal(text).as_tuple().exponent
    assert isinstance(exponent, int)
    return pytest.approx(float(text), rel=0, abs=0.5 * 10.0**exponent)


def study_frame(
    value: Sequence[float],
    learner: Sequence[str],
    environment: Sequence[object] | object,
    position: Sequence[object] | object,
) -> pd.DataFrame:
    return pd.DataFrame(
        {"value": value, "learner": learner, "environment": environment, "position": position}
    )


# --- Two-way additive ANOVA: the kidney data in the statsmodels documentation ---------------

# statsmodels documentation, "Interactions and ANOVA", section "Two-way ANOVA"
# (https://www.statsmodels.org/stable/examples/notebooks/generated/interactions_anova.html,
# cell 40). Days of hospital stay by Duration (1, 2) and Weight (1, 2, 3), ten patients per
# cell; the same table ships with statsmodels as statsmodels/stats/tests/results/data.dat and
# inline in statsmodels/stats/tests/test_anova.py (the notebook downloads it). Listed here per
# (Duration, Weight) in the file's order.
KIDNEY_DAYS = {
    (1, 1): [0, 2, 1, 3, 0, 2, 0, 5, 6, 8],
    (1, 2): [2, 4, 7, 12, 15, 4, 3, 1, 5, 20],
    (1, 3): [15, 10, 8, 5, 25, 16, 7, 30, 3, 27],
    (2, 1): [0, 1, 1, 0, 4, 2, 7, 4, 0, 3],
    (2, 2): [5, 3, 2, 0, 1, 1, 3, 6, 7, 9],
    (2, 3): [10, 8, 12, 3, 7, 15, 4, 9, 6, 1],
}
# The notebook's third table compares np.log(Days+1) ~ C(Weight) with
# np.log(Days+1) ~ C(Duration) + C(Weight, Sum), which is the type II test of Duration in the
# additive model:
#    df_resid        ssr  df_diff   ss_diff         F   Pr(>F)
# 0      57.0  31.964549      0.0       NaN       NaN      NaN
# 1      56.0  29.624856      1.0  2.339693  4.422732  0.03997
KIDNEY_F = "4.422732"
KIDNEY_P = "0.03997"
KIDNEY_SUM_SQ = "2.339693"
KIDNEY_RSS = 29.624856
KIDNEY_DF = (1, 56)


def kidney_frame(weight_as: str) -> pd.DataFrame:
    """The kidney data as sessions: Duration is the learner (1 -> BAM, 2 -> cloning), the
    response is log(Days + 1), and Weight is the environment, the position, or both (the
    study's design, where each environment is taught at its own positions; the overlapping
    dummies span the same space, so the fitted model is the same)."""
    rows = [
        (float(np.log(days + 1)), LEARNERS[duration - 1], weight)
        for (duration, weight), all_days in KIDNEY_DAYS.items()
        for days in all_days
    ]
    value, learner, weight = (list(column) for column in zip(*rows, strict=True))
    names = [f"weight-{w}" for w in weight]
    if weight_as == "environment":
        return study_frame(value, learner, names, 0)
    if weight_as == "position":
        return study_frame(value, learner, "kidney", weight)
    return study_frame(value, learner, names, weight)


@pytest.mark.parametrize("weight_as", ["environment", "position", "environment and position"])
def test_anova_reproduces_the_statsmodels_two_way_kidney_example(weight_as: str) -> None:
    result = anova_learner(kidney_frame(weight_as), LEARNERS)
    assert result.test == "anova_type2"
    assert result.note.startswith("60 sessions")
    assert result.statistic == printed(KIDNEY_F)
    assert result.p_value == printed(KIDNEY_P)
    # The learner's sum of squares: F times the residual mean square of the full model.
    df, df_residual = KIDNEY_DF
    assert result.statistic * df * KIDNEY_RSS / df_residual == printed(KIDNEY_SUM_SQ)
    # Our p is the F(1, 56) tail at our F: the published degrees of freedom.
    assert result.p_value == pytest.approx(
        f_distribution.sf(result.statistic, df, df_residual), rel=1e-9
    )


# --- One within factor: the repeated-measures example shipped with statsmodels --------------

# statsmodels/stats/tests/test_anova_rm.py, test_single_factor_repeated_measures_anova: the
# first 16 rows of statsmodels/stats/tests/results/anova-rm-test-data.csv (subjects 1-8, each
# measured once at B = a and once at B = b), with the result of R's ez::ezANOVA printed in the
# test as [DFn, DFd, F, p] = [1, 7, 22.4, 0.002125452]. With one value per subject and level,
# the repeated-measures error term (B x subject) is the residual of the additive model
# DV ~ C(B) + C(subject), so this is the model our function fits, with B as the learner and
# the subject as the environment (or the position).
RM_DV_AT_A = [7, 3, 6, 6, 5, 8, 6, 7]
RM_DV_AT_B = [7, 11, 9, 11, 10, 10, 11, 11]
RM_P = "0.002125452"
RM_DF = (1, 7)


@pytest.mark.parametrize("subject_as", ["environment", "position"])
def test_anova_reproduces_the_statsmodels_repeated_measures_example(subject_as: str) -> None:
    subjects = list(range(1, 9)) * 2
    frame = study_frame(
        [float(v) for v in RM_DV_AT_A + RM_DV_AT_B],
        [LEARNERS[0]] * 8 + [LEARNERS[1]] * 8,
        [f"subject-{s}" for s in subjects] if subject_as == "environment" else "rm",
        subjects if subject_as == "position" else 0,
    )
    result = anova_learner(frame, LEARNERS)
    # Printed as 22.4; by hand it is exactly that: the differences b - a are
    # 0, 8, 3, 5, 5, 2, 5, 4 (mean 4, sum of squared deviations 40), and F is the paired t
    # squared, 4^2 / (40 / 7 / 8) = 22.4.
    assert result.statistic == pytest.approx(22.4, rel=1e-12)
    assert result.p_value == printed(RM_P)
    assert result.p_value == pytest.approx(f_distribution.sf(22.4, *RM_DF), rel=1e-9)


# --- Welch's t-test ---------------------------------------------------------------------------


def test_welch_reproduces_r_t_test_values_shipped_with_scipy() -> None:
    # scipy/stats/tests/test_stats.py, TestTTestInd.test_ttest_ind_with_uneq_var: values of
    # R's t.test(a, b) (Welch by default) printed with options(digits=20); the same values
    # are in statsmodels/stats/tests/test_weightstats.py, test_ttest_ind_with_uneq_var.
    b = [1.1, 2.9, 4.2]
    result = welch_t_test([1.0, 2.0, 3.0], b)
    assert result.test == "welch_t_test"
    assert result.statistic == pytest.approx(-0.686495127355726265, rel=1e-12)
    assert result.p_value == pytest.approx(0.53619490753126686, rel=1e-12)
    result = welch_t_test([1.0, 2.0, 3.0, 4.0], b)
    assert result.statistic == pytest.approx(-0.210866331595072315, rel=1e-12)
    assert result.p_value == pytest.approx(0.84354139131608252, rel=1e-12)


# scipy.stats.ttest_ind docstring, Examples, with equal_var = False, as published in the SciPy
# 1.x reference before the examples switched to an unseeded Generator (for instance
# https://docs.scipy.org/doc/scipy-1.5.3/reference/generated/scipy.stats.ttest_ind.html):
# np.random.seed(12345678), then rvs1, ..., rvs5 drawn in turn with stats.norm.rvs. NumPy keeps
# the legacy RandomState stream fixed, so a RandomState(12345678) passed as random_state draws
# the same samples without touching the global generator. The docs print 17 significant
# digits; SciPy today agrees to about 14, so the comparison is to 1e-12.
SCIPY_DOCS_WELCH = {
    # sample: (loc, scale, size, printed t, printed p) for ttest_ind(rvs1, sample, False)
    "rvs2": (5, 10, 500, 0.26833823296239279, 0.78849452749500748),
    "rvs3": (5, 20, 500, -0.46580283298287162, 0.64149646246569292),
    "rvs4": (5, 20, 100, -0.69712570584654099, 0.48716927725402048),
    "rvs5": (8, 20, 100, -0.94365973617132992, 0.34744170334794122),
}


def test_welch_reproduces_the_seeded_scipy_documentation_examples() -> None:
    random_state = np.random.RandomState(12345678)
    rvs1 = norm.rvs(loc=5, scale=10, size=500, random_state=random_state)
    for name, (loc, scale, size, t, p) in SCIPY_DOCS_WELCH.items():
        sample = norm.rvs(loc=loc, scale=scale, size=size, random_state=random_state)
        result = welch_t_test(rvs1, sample)
        assert result.statistic == pytest.approx(t, rel=1e-12), name
        assert result.p_value == pytest.approx(p, rel=1e-12), name
