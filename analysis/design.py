"""Success at a threshold compared within the study's blocks.

In the paper's design every participant teaches one agent of each learner in each environment
of their domain, in a random order: a *block* is one participant's sessions in one
environment, and the learner varies within it. The tests here take the block as the unit, so
a teacher's skill and effort, shared by the sessions of a block, cancels out of every
comparison:

- ``cochran_q``: Cochran's Q over the learners, on the blocks that have a session of each;
- ``mcnemar_midp``: the exact McNemar test between two learners, as a mid-p value, on the
  blocks that have a session of both (only the discordant blocks count);
- ``permutation_test``: the learner labels shuffled within each block, as the randomisation
  of the study would have shuffled them, for every learner at once and for each pair.

Effect sizes: the paired risk difference (Agresti and Min's adjusted Wald interval) and the
conditional odds ratio of the discordant blocks (exact interval from the binomial).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from analysis.stats import reached_column

Z95 = 1.959963984540054  # the standard normal's 97.5% quantile
PERMUTATIONS = 10_000
SEED = 20_240_501
CHUNK = 500  # shuffles drawn at a time
TIE = 1e-9  # statistics within rounding of the observed count as at least it


@dataclass(frozen=True)
class Paired:
    """The blocks with a session of both learners, by whether each reached the threshold."""

    both: int
    baseline_only: int
    alternative_only: int
    neither: int

    @property
    def blocks(self) -> int:
        return self.both + self.baseline_only + self.alternative_only + self.neither


def block_outcomes(summary: pd.DataFrame, threshold: float) -> pd.DataFrame:
    """One row per block (``participant_id``, ``environment``), one column per learner: 1.0
    when that learner's session of the block reached ``threshold``, 0.0 when not, NaN when the
    block has no session of it. A block with two sessions of a learner (a participant who
    came back) keeps the first by position."""
    frame = summary.sort_values("position", kind="stable").drop_duplicates(
        ["participant_id", "environment", "learner"], keep="first"
    )
    frame = frame.assign(outcome=frame[reached_column(threshold)].astype(float))
    wide = frame.pivot(index=["participant_id", "environment"], columns="learner", values="outcome")
    wide.columns.name = None
    return wide


def paired_counts(blocks: pd.DataFrame, baseline: str, alternative: str) -> Paired:
    pair = blocks[[baseline, alternative]].dropna()
    b, a = pair[baseline] == 1, pair[alternative] == 1
    return Paired(
        both=int((b & a).sum()),
        baseline_only=int((b & ~a).sum()),
        alternative_only=int((~b & a).sum()),
        neither=int((~b & ~a).sum()),
    )


def mcnemar_midp(baseline_only: int, alternative_only: int) -> float:
    """The two-sided mid-p value of the exact McNemar test: with n discordant blocks and
    m = min of the two counts, 2 P(X <= m) - P(X = m) for X ~ Binomial(n, 1/2), at most 1
    (Fagerland, Lydersen and Laake 2013). 1 when no block is discordant."""
    from scipy.stats import binom

    n = baseline_only + alternative_only
    if n == 0:
        return 1.0
    m = min(baseline_only, alternative_only)
    return float(min(1.0, 2 * binom.cdf(m, n, 0.5) - binom.pmf(m, n, 0.5)))


def risk_difference(paired: Paired) -> tuple[float, float, float]:
    """The alternative's success rate minus the baseline's over the paired blocks, with
    Agresti and Min's (2005) 95% interval: the Wald interval of the paired difference after
    adding 1/2 to each of the four cells. NaN without blocks."""
    n = paired.blocks
    if n == 0:
        return math_nan3()
    estimate = (paired.alternative_only - paired.baseline_only) / n
    b, c, total = paired.baseline_only + 0.5, paired.alternative_only + 0.5, n + 2.0
    shifted = (c - b) / total
    se = np.sqrt(((b + c) - (c - b) ** 2 / total) / total**2)
    low, high = max(-1.0, shifted - Z95 * se), min(1.0, shifted + Z95 * se)
    return float(estimate), float(low), float(high)


def conditional_odds_ratio(paired: Paired) -> tuple[float, float, float]:
    """The odds ratio of success for the alternative against the baseline within blocks,
    ``alternative_only / baseline_only`` (the conditional maximum likelihood estimate), with
    the exact 95% interval from the Clopper-Pearson interval of the share of discordant blocks
    that favour the alternative. NaN without discordant blocks."""
    from scipy.stats import beta

    b, c = paired.baseline_only, paired.alternative_only
    n = b + c
    if n == 0:
        return math_nan3()
    low_share = 0.0 if c == 0 else float(beta.ppf(0.025, c, n - c + 1))
    high_share = 1.0 if c == n else float(beta.ppf(0.975, c + 1, n - c))
    estimate = np.inf if b == 0 else c / b
    low = low_share / (1 - low_share)
    high = np.inf if high_share >= 1 else high_share / (1 - high_share)
    return float(estimate), float(low), float(high)


def math_nan3() -> tuple[float, float, float]:
    return float("nan"), float("nan"), float("nan")


@dataclass(frozen=True)
class Omnibus:
    statistic: float
    df: int
    p_value: float
    blocks: int


def cochran_q(blocks: pd.DataFrame, learners: Sequence[str]) -> Omnibus | None:
    """Cochran's Q (statsmodels' ``cochrans_q``) over ``learners``, on the blocks with a
    session of each; its p-value is the chi-squared approximation with k - 1 degrees of
    freedom. None with fewer than two learners or no complete block; Q is 0 (p 1) when every
    complete block is all successes or all failures."""
    from statsmodels.stats.contingency_tables import cochrans_q as statsmodels_q

    if len(learners) < 2:
        return None
    complete = blocks[list(learners)].dropna()
    if complete.empty:
        return None
    row_sums = complete.sum(axis=1)
    informative = complete.loc[(row_sums > 0) & (row_sums < len(learners))]
    if informative.empty:
        return Omnibus(0.0, len(learners) - 1, 1.0, len(complete))
    result = statsmodels_q(informative.to_numpy(dtype=int))
    return Omnibus(float(result.statistic), int(result.df), float(result.pvalue), len(complete))


@dataclass(frozen=True)
class Permutation:
    p_all: float  # every learner at once
    p_pairs: dict[str, float]  # baseline against each alternative
    permutations: int
    blocks: int


def permutation_test(
    blocks: pd.DataFrame,
    baseline: str,
    alternatives: Sequence[str],
    *,
    permutations: int = PERMUTATIONS,
    seed: int = SEED,
) -> Permutation | None:
    """The learner labels shuffled at random within each block (among the learners the block
    has), ``permutations`` times: the p-value is (1 + the shuffles whose statistic is at least
    the observed) / (1 + shuffles). For every learner at once the statistic is the sum over
    learners of (successes - their mean under shuffling)^2; for a pair, |baseline successes -
    alternative successes - its mean under shuffling|. None without a block of two learners."""
    learners = [baseline, *alternatives]
    values = blocks[learners].to_numpy(dtype=float)
    present = ~np.isnan(values)
    keep = present.sum(axis=1) >= 2
    values, present = values[keep], present[keep]
    if not len(values):
        return None
    outcomes = np.where(present, values, 0.0)
    # Each block's present outcomes first: a shuffle deals them out to the present learners.
    ordered = np.argsort(np.where(present, 0.0, 1.0), axis=1, kind="stable")
    by_rank = np.take_along_axis(outcomes, ordered, axis=1)
    expected = (present * (outcomes.sum(axis=1) / present.sum(axis=1))[:, None]).sum(axis=0)
    observed = outcomes.sum(axis=0)
    pair_blocks = {j: present[:, 0] & present[:, j] for j in range(1, len(learners))}
    # In a block with both learners each is equally likely to get either outcome, so the
    # difference of a pair's successes has mean 0 under shuffling.
    observed_pairs = {
        j: abs(float((outcomes[b, 0] - outcomes[b, j]).sum())) for j, b in pair_blocks.items()
    }
    at_least_all = 0
    at_least_pairs = dict.fromkeys(pair_blocks, 0)
    rng = np.random.default_rng(seed)
    for start in range(0, permutations, CHUNK):
        size = min(CHUNK, permutations - start)
        # Random keys, the absent learners' pushed last, ranked within each block.
        keys = rng.random((size, *values.shape)) + np.where(present, 0.0, 2.0)
        slots = np.argsort(np.argsort(keys, axis=2), axis=2)
        shuffled = np.take_along_axis(np.broadcast_to(by_rank, keys.shape), slots, axis=2)
        shuffled = np.where(present, shuffled, 0.0)
        totals = shuffled.sum(axis=1)  # shuffles x learners
        statistic = ((totals - expected) ** 2).sum(axis=1)
        at_least_all += int(np.sum(statistic >= float(((observed - expected) ** 2).sum()) - TIE))
        for j, both in pair_blocks.items():
            pair = np.abs((shuffled[:, both, 0] - shuffled[:, both, j]).sum(axis=1))
            at_least_pairs[j] += int(np.sum(pair >= observed_pairs[j] - TIE))
    p_all = (1 + at_least_all) / (1 + permutations)
    pairs = {
        learners[j]: (1 + count) / (1 + permutations)
        for j, count in at_least_pairs.items()
        if pair_blocks[j].any()
    }
    return Permutation(p_all, pairs, permutations, len(values))
