"""The design-respecting statistics against published values and independent computations."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pandas as pd
import pytest
from scipy.optimize import minimize_scalar
from scipy.stats import binom

from analysis import design, models, survival

# --- McNemar mid-p ------------------------------------------------------------------------


def test_mcnemar_midp_of_the_published_example() -> None:
    """Fagerland, Lydersen and Laake (2013, BMC Med Res Methodol 13:91), Table 1: 1 and 7
    discordant pairs; exact conditional p 0.070, mid-p 0.039. By hand from Binomial(8, 1/2):
    2 P(X <= 1) - P(X = 1) = 2 * 9/256 - 8/256 = 10/256."""
    assert design.mcnemar_midp(1, 7) == pytest.approx(10 / 256, abs=1e-12)
    assert design.mcnemar_midp(7, 1) == pytest.approx(10 / 256, abs=1e-12)
    assert round(design.mcnemar_midp(1, 7), 3) == 0.039


def test_mcnemar_midp_edges() -> None:
    assert design.mcnemar_midp(0, 0) == 1.0
    assert design.mcnemar_midp(4, 4) == 1.0  # 2 P(X<=4) - P(X=4) = 1 exactly
    # 0 against 5: 2 * (1/32) - 1/32
    assert design.mcnemar_midp(0, 5) == pytest.approx(1 / 32)


# --- Cochran's Q --------------------------------------------------------------------------

# WaveMetrics, Igor Pro's StatsCochranTest documentation: 9 blocks, 5 groups.
WAVE1 = [
    [0, 0, 0, 0, 1],
    [0, 0, 0, 0, 1],
    [0, 0, 0, 1, 1],
    [0, 1, 0, 1, 1],
    [0, 1, 0, 1, 0],
    [1, 1, 0, 1, 0],
    [1, 1, 0, 0, 0],
    [1, 0, 0, 0, 0],
    [1, 0, 0, 0, 0],
]
WAVE2 = [
    [0, 0, 0, 0, 1],
    [0, 0, 0, 0, 1],
    [0, 0, 0, 1, 1],
    [0, 1, 0, 1, 1],
    [1, 1, 0, 1, 1],
    [1, 1, 0, 1, 1],
    [1, 1, 0, 1, 0],
    [1, 1, 0, 0, 0],
    [1, 0, 0, 0, 0],
]


@pytest.mark.parametrize(
    ("table", "statistic", "p_value"), [(WAVE1, 5.56522, 0.234056), (WAVE2, 10.3636, 0.0347281)]
)
def test_cochran_q_of_the_published_examples(table, statistic, p_value) -> None:
    blocks = pd.DataFrame(np.array(table, dtype=float), columns=list("abcde"))
    found = design.cochran_q(blocks, list("abcde"))
    assert found is not None
    assert found.statistic == pytest.approx(statistic, abs=1e-4)
    assert found.p_value == pytest.approx(p_value, abs=1e-6)
    assert (found.df, found.blocks) == (4, 9)
    # By hand: Q = (k-1) (k sum C_j^2 - N^2) / (k N - sum R_i^2).
    x = np.array(table)
    k, n = x.shape[1], x.sum()
    by_hand = (
        (k - 1) * (k * (x.sum(axis=0) ** 2).sum() - n**2) / (k * n - (x.sum(axis=1) ** 2).sum())
    )
    assert found.statistic == pytest.approx(by_hand)


def test_cochran_q_leaves_out_incomplete_blocks_and_ignores_uniform_ones() -> None:
    base = pd.DataFrame(np.array(WAVE1, dtype=float), columns=list("abcde"))
    extra = pd.DataFrame(
        [[1, 1, 1, 1, 1], [0, 0, 0, 0, 0], [1, np.nan, 0, 0, 0]], columns=list("abcde")
    )
    found = design.cochran_q(pd.concat([base, extra]), list("abcde"))
    assert found is not None and found.blocks == 11  # the incomplete block is left out
    assert found.statistic == pytest.approx(5.56522, abs=1e-4)


# --- The permutation test -----------------------------------------------------------------


def test_with_two_learners_the_permutation_test_is_the_exact_mcnemar_test() -> None:
    """Swapping two labels within a block flips the sign of a discordant block: the shuffle
    distribution of the difference is 2 Binomial(n, 1/2) - n, so the p-value is the exact
    (not mid-p) McNemar test's: with 3 and 9 discordant blocks, 2 P(X <= 3), X ~ Bin(12, 1/2)."""
    rows = [(1, 0)] * 3 + [(0, 1)] * 9 + [(1, 1)] * 5 + [(0, 0)] * 4
    blocks = pd.DataFrame(rows, columns=["bam", "cloning"], dtype=float)
    found = design.permutation_test(blocks, "bam", ["cloning"], permutations=40_000)
    assert found is not None
    exact = 2 * binom.cdf(3, 12, 0.5)
    se = math.sqrt(exact * (1 - exact) / 40_000)
    assert abs(found.p_pairs["cloning"] - exact) < 4 * se
    assert found.p_all == pytest.approx(found.p_pairs["cloning"])  # one pair: the same test


def test_the_permutation_test_against_every_shuffle() -> None:
    """Four blocks of three learners: all 6^4 shuffles enumerated by hand."""
    outcomes = np.array([[1, 0, 0], [1, 1, 0], [1, 0, 0], [0, 1, 0]], dtype=float)
    blocks = pd.DataFrame(outcomes, columns=["bam", "model-based", "cloning"])
    expected = outcomes.sum(axis=1).sum() / 3  # per learner
    observed_all = ((outcomes.sum(axis=0) - expected) ** 2).sum()
    observed_pair = abs(outcomes[:, 0].sum() - outcomes[:, 2].sum())
    at_least_all = at_least_pair = total = 0
    orders = list(itertools.permutations(range(3)))
    for choice in itertools.product(orders, repeat=4):
        shuffled = np.array([row[list(order)] for row, order in zip(outcomes, choice, strict=True)])
        totals = shuffled.sum(axis=0)
        at_least_all += ((totals - expected) ** 2).sum() >= observed_all - 1e-9
        at_least_pair += abs(totals[0] - totals[2]) >= observed_pair - 1e-9
        total += 1
    found = design.permutation_test(blocks, "bam", ["model-based", "cloning"], permutations=40_000)
    assert found is not None
    for p, exact in (
        (found.p_all, at_least_all / total),
        (found.p_pairs["cloning"], at_least_pair / total),
    ):
        assert abs(p - exact) < 4 * math.sqrt(exact * (1 - exact) / 40_000) + 1e-4


def test_the_permutation_test_shuffles_only_the_learners_a_block_has() -> None:
    """A block without Behavioral Cloning keeps its two outcomes between the other two: a
    block of one success and a missing learner cannot give the missing one a success."""
    blocks = pd.DataFrame([[1.0, 0.0, np.nan]] * 6, columns=["bam", "model-based", "cloning"])
    found = design.permutation_test(blocks, "bam", ["model-based", "cloning"], permutations=4000)
    assert found is not None
    assert "cloning" not in found.p_pairs  # no block has both
    # bam against model-based: 6 discordant blocks all one way: exact p 2 / 2^6.
    assert found.p_pairs["model-based"] == pytest.approx(2 / 64, abs=0.012)


# --- Effect sizes -------------------------------------------------------------------------


def test_the_paired_risk_difference_by_hand() -> None:
    """Agresti and Min (2005): 1/2 added to each cell, then the Wald interval of the paired
    difference. Both 5, baseline only 3, alternative only 9, neither 4 (21 blocks)."""
    paired = design.Paired(both=5, baseline_only=3, alternative_only=9, neither=4)
    estimate, low, high = design.risk_difference(paired)
    assert estimate == pytest.approx(6 / 21)
    n, b, c = 23.0, 3.5, 9.5
    centre = (c - b) / n
    se = math.sqrt((b + c) - (c - b) ** 2 / n) / n
    assert (low, high) == pytest.approx((centre - 1.959964 * se, centre + 1.959964 * se))


def test_the_conditional_odds_ratio_and_its_exact_interval() -> None:
    """9 against 3 discordant blocks: the ratio is 3; at each end of the interval the share
    p = OR / (1 + OR) makes the binomial tail of the observed count exactly 2.5%."""
    paired = design.Paired(both=5, baseline_only=3, alternative_only=9, neither=4)
    estimate, low, high = design.conditional_odds_ratio(paired)
    assert estimate == pytest.approx(3.0)
    assert binom.sf(8, 12, low / (1 + low)) == pytest.approx(0.025, abs=1e-9)  # P(X >= 9)
    assert binom.cdf(9, 12, high / (1 + high)) == pytest.approx(0.025, abs=1e-9)  # P(X <= 9)
    estimate, low, high = design.conditional_odds_ratio(design.Paired(2, 0, 4, 1))
    assert estimate == math.inf and high == math.inf and low > 0


# --- Kaplan-Meier and Cox -----------------------------------------------------------------

# Freireich et al. (1963) remission times in weeks, the 6-MP group (0: censored), as in
# Kleinbaum and Klein, Survival Analysis (3rd ed.), chapter 2; and the placebo group.
SIX_MP = [(6, 1), (6, 1), (6, 1), (6, 0), (7, 1), (9, 0), (10, 1), (10, 0), (11, 0), (13, 1),
          (16, 1), (17, 0), (19, 0), (20, 0), (22, 1), (23, 1), (25, 0), (32, 0), (32, 0),
          (34, 0), (35, 0)]  # fmt: skip
PLACEBO = [1, 1, 2, 2, 3, 4, 4, 5, 5, 8, 8, 8, 8, 11, 11, 12, 12, 15, 17, 22, 23]


def leukaemia() -> pd.DataFrame:
    rows = [("bam", t, bool(e)) for t, e in SIX_MP] + [("cloning", t, True) for t in PLACEBO]
    return pd.DataFrame(
        {
            "participant_id": "one",
            "environment": "trial",
            "learner": [r[0] for r in rows],
            "position": 0,
            "time": [float(r[1]) for r in rows],
            "event": [r[2] for r in rows],
        }
    )


def test_kaplan_meier_of_the_published_example() -> None:
    six_mp = leukaemia().query("learner == 'bam'")
    times, survival_share = survival.kaplan_meier(six_mp)
    assert list(times) == [6, 7, 10, 13, 16, 22, 23]
    # Kleinbaum and Klein: .8571, .8067, .7529, .6902, .6275, .5378, .4482; by hand the first
    # two are 18/21 and 18/21 * 16/17.
    assert survival_share == pytest.approx(
        [0.8571, 0.8067, 0.7529, 0.6902, 0.6275, 0.5378, 0.4482], abs=1e-4
    )
    assert survival_share[1] == pytest.approx(18 / 21 * 16 / 17)
    median = survival.median_time(six_mp)
    assert (median.sessions, median.events, median.median) == (21, 9, 23.0)
    assert median.high == math.inf  # the curve never falls to the interval's upper end
    placebo = survival.median_time(leukaemia().query("learner == 'cloning'"))
    assert placebo.median == 8.0  # the published median of the placebo group


def test_cox_of_the_published_example() -> None:
    """The placebo group's hazard against 6-MP's, Efron's method for ties: R's
    ``coxph(Surv(time, cens) ~ treat, data = MASS::gehan)`` gives coefficient 1.572, standard
    error 0.412, exp 4.817 (95% 2.147 to 10.81), Wald p 0.00014."""
    found = survival.cox_stratified(leukaemia(), "bam", "cloning")
    assert found.ratio == pytest.approx(4.817, abs=1e-3)
    assert (found.low, found.high) == pytest.approx((2.147, 10.81), abs=2e-3)
    assert found.p_value == pytest.approx(0.00014, abs=1e-5)
    assert found.blocks == 1


def test_the_stratified_cox_model_against_its_partial_likelihood_by_hand() -> None:
    """Blocks of two sessions without tied times: each block that saw an event adds
    log(exp(b x_first) / sum over its sessions at risk), maximised here by hand."""
    rng = np.random.default_rng(7)
    rows = []
    for block in range(30):
        for learner in ("bam", "cloning"):
            time = rng.exponential(1.0 if learner == "bam" else 0.6) * (1 + block % 3)
            censored_at = 2.5
            rows.append((f"p{block}", learner, min(time, censored_at), time <= censored_at))
    frame = pd.DataFrame(rows, columns=["participant_id", "learner", "time", "event"])
    frame["environment"], frame["position"] = "e", 0

    def partial(beta: float) -> float:
        total = 0.0
        for _, block in frame.groupby("participant_id"):
            x = (block["learner"] == "cloning").to_numpy(float)
            t, e = block["time"].to_numpy(), block["event"].to_numpy()
            for i in np.flatnonzero(e):
                at_risk = t >= t[i]
                total += beta * x[i] - math.log(np.exp(beta * x[at_risk]).sum())
        return -total

    by_hand = minimize_scalar(partial, bounds=(-5, 5), method="bounded").x
    found = survival.cox_stratified(frame, "bam", "cloning")
    assert found.ratio is not None and math.log(found.ratio) == pytest.approx(by_hand, abs=1e-4)


def test_cox_without_events_for_a_learner_is_not_estimated() -> None:
    frame = leukaemia()
    frame.loc[frame["learner"] == "cloning", "event"] = False
    found = survival.cox_stratified(frame, "bam", "cloning")
    assert found.ratio is None and "cannot be estimated" in found.note


def test_event_times_censor_at_the_last_evaluation() -> None:
    summary = pd.DataFrame(
        {
            "session_id": ["a", "b", "c"],
            "participant_id": "p",
            "environment": "e",
            "learner": ["bam", "cloning", "cloning"],
            "position": [0, 1, 2],
            "evaluations": [3, 4, 0],
            "reached_50": [True, False, False],
            "episodes_50": pd.array([2, None, None], dtype="Int64"),
        }
    )
    evaluations = pd.DataFrame(
        {"session_id": ["a"] * 3 + ["b"] * 4, "episodes": [1, 2, 5, 1, 3, 6, 9]}
    )
    times = survival.event_times(summary, evaluations, "episodes", 0.5)
    assert times["time"].tolist() == [2.0, 9.0]  # the untaught session is left out
    assert times["event"].tolist() == [True, False]


# --- The GEE model ------------------------------------------------------------------------


def test_gee_in_a_balanced_block_design_gives_the_sample_odds_ratio() -> None:
    """With one session of each learner per participant and no other term, the estimating
    equations make each learner's fitted rate its observed rate, whatever the working
    correlation: the odds ratio is the sample odds ratio, (6/10 / 4/10) / (3/10 / 7/10)."""
    bam = [1] * 6 + [0] * 4
    cloning = [1, 0, 1, 0, 0, 1, 0, 0, 0, 0]
    summary = pd.DataFrame(
        {
            "participant_id": [f"p{i}" for i in range(10)] * 2,
            "environment": "e",
            "learner": ["bam"] * 10 + ["cloning"] * 10,
            "position": 0,
            "reached_50": [bool(v) for v in bam + cloning],
        }
    )
    found = models.gee_odds_ratios(summary, 0.5, "bam", ["cloning"], pooled=False)["cloning"]
    assert found.ratio == pytest.approx((3 / 7) / (6 / 4), rel=1e-6)
    assert found.low is not None and found.high is not None
    assert found.low < found.ratio < found.high
    assert found.p_value is not None and 0 < found.p_value < 1


def test_gee_refuses_separated_data() -> None:
    summary = pd.DataFrame(
        {
            "participant_id": ["p1", "p2", "p1", "p2"],
            "environment": "e",
            "learner": ["bam", "bam", "cloning", "cloning"],
            "position": 0,
            "reached_50": [True, True, False, True],
        }
    )
    found = models.gee_odds_ratios(summary, 0.5, "bam", ["cloning"], pooled=False)["cloning"]
    assert found.ratio is None and "every BAM session reached it" in found.note


def test_gee_whose_interval_is_not_a_float_is_not_estimated() -> None:
    """Success follows the position (both sessions at 0 and 4 reached the threshold, one of
    the six at 2 and 3) while each learner has successes and failures: the fit's standard error
    makes the interval's bound overflow a float, which is reported, not raised."""
    summary = pd.DataFrame(
        {
            "participant_id": ["p0", "p0", "p1", "p1", "p2", "p2", "p3", "p3"],
            "environment": "e",
            "learner": ["bam", "cloning"] * 4,
            "position": [3, 2, 3, 2, 4, 0, 3, 2],
            "reached_50": [False, False, False, True, True, True, False, False],
        }
    )
    found = models.gee_odds_ratios(summary, 0.5, "bam", ["cloning"], pooled=False)["cloning"]
    assert found.ratio is None and found.low is None and found.high is None
    assert "did not converge" in found.note
