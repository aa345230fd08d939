"""The design-respecting tests checked by simulation: studies drawn from a known model
(``simulate.py``: participants of widely different skill) with learners that do not differ
hold the tests' level, and with a real difference the tests find it at least as often as the
paper's pooled Fisher test.

The level check is a statistical statement: if a test rejected at most 5% of the time, its
rejection count over n null studies would exceed the binomial's 99.9% quantile with
probability below 0.1%; a count above it shows a level above 5%. Every draw is seeded.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy.stats import binom

from analysis import design, models, survival
from analysis.stats import fisher_success, reached_column

from .simulate import LEARNERS, THRESHOLD, simulate_study

pytestmark = pytest.mark.slow  # a few minutes of simulated studies: CI runs it, the fast tier not

ALPHA = 0.05
PARTICIPANTS = 16  # 32 blocks, 96 sessions a study
NULL_STUDIES = 240  # the fast tests (McNemar, Cochran's Q, permutation, Fisher)
MODEL_NULL_STUDIES = 80  # the models (GEE, Cox), which take longer to fit
POWER_STUDIES = 50
EFFECT = 1.0  # Behavioral Cloning's lower log odds per episode under the alternative
SHUFFLES = 400


def fast_tests(summary: pd.DataFrame) -> dict[str, float]:
    blocks = design.block_outcomes(summary, THRESHOLD)
    paired = design.paired_counts(blocks, "bam", "cloning")
    q = design.cochran_q(blocks, list(LEARNERS))
    permuted = design.permutation_test(
        blocks, "bam", ["model-based", "cloning"], permutations=SHUFFLES, seed=len(summary)
    )
    assert q is not None and permuted is not None
    reached = reached_column(THRESHOLD)
    b = summary.loc[summary["learner"] == "bam", reached]
    a = summary.loc[summary["learner"] == "cloning", reached]
    fisher = fisher_success(int(b.sum()), len(b), int(a.sum()), len(a)).p_value
    assert fisher is not None
    return {
        "mcnemar_midp": design.mcnemar_midp(paired.baseline_only, paired.alternative_only),
        "cochran_q": q.p_value,
        "permutation_all": permuted.p_all,
        "permutation_pair": permuted.p_pairs["cloning"],
        "fisher_pooled": fisher,
    }


def model_tests(summary: pd.DataFrame, evaluations: pd.DataFrame) -> dict[str, float]:
    gee = models.gee_odds_ratios(summary, THRESHOLD, "bam", ["cloning"], pooled=True)
    times = survival.event_times(summary, evaluations, "episodes", THRESHOLD)
    cox = survival.cox_stratified(times, "bam", "cloning")
    # A study where a learner's sessions all (or none) reached it has no finite estimate; it
    # counts as not rejected (a test not done rejects nothing).
    return {
        "gee_logistic": 1.0 if gee["cloning"].p_value is None else gee["cloning"].p_value,
        "cox_stratified": 1.0 if cox.p_value is None else cox.p_value,
    }


def rejections(p_values: list[dict[str, float]]) -> dict[str, int]:
    return {name: sum(p[name] <= ALPHA for p in p_values) for name in p_values[0]}


def level_bound(studies: int) -> int:
    """The most rejections a test of level 5% gives in ``studies`` null studies, but with
    probability below 0.1%."""
    return int(binom.ppf(0.999, studies, ALPHA))


@pytest.fixture(scope="module")
def null_balanced() -> dict[str, int]:
    rng = np.random.default_rng(1)
    return rejections(
        [fast_tests(simulate_study(rng, PARTICIPANTS)[0]) for _ in range(NULL_STUDIES)]
    )


def test_the_fast_tests_hold_their_level_in_the_balanced_design(
    null_balanced: dict[str, int],
) -> None:
    bound = level_bound(NULL_STUDIES)
    for name in ("mcnemar_midp", "cochran_q", "permutation_all", "permutation_pair"):
        assert null_balanced[name] <= bound, (name, null_balanced[name], bound)
    # The simulation is not degenerate: the tests do reject now and then under the null.
    assert sum(null_balanced.values()) > 0


def test_the_fast_tests_hold_their_level_when_balance_breaks() -> None:
    """A fifth of the sessions missing at random, as after returns and exclusions."""
    rng = np.random.default_rng(2)
    counts = rejections(
        [fast_tests(simulate_study(rng, PARTICIPANTS, missing=0.2)[0]) for _ in range(NULL_STUDIES)]
    )
    bound = level_bound(NULL_STUDIES)
    for name in ("mcnemar_midp", "cochran_q", "permutation_all", "permutation_pair"):
        assert counts[name] <= bound, (name, counts[name], bound)


def test_the_models_hold_their_level() -> None:
    rng = np.random.default_rng(3)
    counts = rejections(
        [model_tests(*simulate_study(rng, PARTICIPANTS)) for _ in range(MODEL_NULL_STUDIES)]
    )
    bound = level_bound(MODEL_NULL_STUDIES)
    for name, count in counts.items():
        assert count <= bound, (name, count, bound)


def test_with_a_real_effect_the_tests_find_it_at_least_as_often_as_pooled_fisher() -> None:
    rng = np.random.default_rng(4)
    p_values = []
    for _ in range(POWER_STUDIES):
        summary, evaluations = simulate_study(rng, PARTICIPANTS, EFFECT)
        p_values.append({**fast_tests(summary), **model_tests(summary, evaluations)})
    counts = rejections(p_values)
    fisher = counts["fisher_pooled"]
    assert fisher > 0  # the effect is real enough for the paper's test to see it at times
    for name in ("mcnemar_midp", "permutation_pair", "gee_logistic", "cox_stratified"):
        assert counts[name] >= fisher, (name, counts[name], fisher)
    # Every learner at once, with Model-Based IRL alike to BAM, still has the power.
    assert counts["cochran_q"] >= fisher
