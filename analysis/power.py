"""Power by simulation: how often the planned analysis sees one learner beat another.

From a bank of simulated sessions (``analysis.power_bank``), a simulated study of N
participants is made as the study assigns them: participant i to the study's domains in
turn (balanced), each drawn at random, with replacement, from the bank's participants of
that domain, with all their sessions, so that a participant's skill and effort are shared by
their sessions as a person's are. On each simulated study the planned test of "the first
learner reaches the threshold in more sessions than the second", over all environments, is
run as ``bam-study analyze`` runs it:

- ``mcnemar_midp``: the exact McNemar mid-p test on the blocks (one participant's two
  sessions in one environment; ``analysis.design``), the design-respecting primary test;
- ``fisher_exact``: the paper's Fisher's exact test on the sessions pooled over environments.

The power at N is the share of the simulated studies in which the test rejects at ``alpha``
*and* the first learner is ahead (``power``); ``rejections`` counts either direction, which is
the test's level when the learners do not differ. ``no_difference`` makes that case from the
same bank: within each block the two sessions' outcomes are swapped at random, as under the
randomisation's null hypothesis, so the power shows the test's level with the bank's
participants.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cache

import numpy as np
import pandas as pd

from analysis.power_bank import first_reached
from analysis.stats import fisher_success

TESTS = ("mcnemar_midp", "fisher_exact")
TEST_NAMES = {
    "mcnemar_midp": "exact McNemar mid-p on the blocks",
    "fisher_exact": "Fisher's exact test, sessions pooled (the paper's)",
}
POWER_COLUMNS = (
    "participants",
    "test",
    "studies",
    "power",
    "power_low",
    "power_high",
    "rejections",
    "baseline_sessions_reached",
    "alternative_sessions_reached",
)
TARGET = 0.8
Z95 = 1.959963984540054


@dataclass(frozen=True)
class Blocks:
    """Per bank participant of each domain, the counts their blocks bring to a study:
    blocks where both learners reached the threshold, only the first, only the second; and
    their number of blocks (the environments of the domain they have both learners in)."""

    domains: tuple[str, ...]
    both: tuple[np.ndarray, ...]
    first_only: tuple[np.ndarray, ...]
    second_only: tuple[np.ndarray, ...]
    blocks: tuple[np.ndarray, ...]


def bank_blocks(bank: pd.DataFrame, first: str, second: str, threshold: float) -> Blocks:
    """The bank's sessions of the two learners reduced to ``Blocks``, domain by domain in the
    bank's order."""
    reached = bank.assign(
        reached=[first_reached(curve, threshold) is not None for curve in bank["curve"]]
    )
    wide = (
        reached.loc[reached["learner"].isin([first, second])]
        .pivot_table(
            index=["domain", "participant", "environment"],
            columns="learner",
            values="reached",
            aggfunc="first",
        )
        .dropna()
        .astype(bool)
    )
    names = tuple(dict.fromkeys(bank["domain"]))
    counts: dict[str, list[np.ndarray]] = {"both": [], "first": [], "second": [], "blocks": []}
    for domain in names:
        rows = wide.xs(domain, level="domain") if domain in wide.index.get_level_values(0) else None
        participants = np.sort(bank.loc[bank["domain"] == domain, "participant"].unique())
        if rows is None or rows.empty:
            zeros = np.zeros(len(participants), dtype=np.int64)
            for key in counts:
                counts[key].append(zeros)
            continue
        a, b = rows[first], rows[second]
        by = rows.index.get_level_values("participant")

        def per(
            values: pd.Series, by: pd.Index = by, participants: np.ndarray = participants
        ) -> np.ndarray:
            return values.groupby(by).sum().reindex(participants, fill_value=0).to_numpy(np.int64)

        counts["both"].append(per(a & b))
        counts["first"].append(per(a & ~b))
        counts["second"].append(per(~a & b))
        counts["blocks"].append(per(pd.Series(True, index=rows.index)))
    return Blocks(
        names,
        tuple(counts["both"]),
        tuple(counts["first"]),
        tuple(counts["second"]),
        tuple(counts["blocks"]),
    )


def reach_shares(blocks: Blocks) -> tuple[float, float]:
    """The shares of the bank's blocks in which each learner's session reached the threshold
    (each domain weighted as a study of participants assigned in turn weights it)."""
    first = second = 0.0
    for both, only_first, only_second, count in zip(
        blocks.both, blocks.first_only, blocks.second_only, blocks.blocks, strict=True
    ):
        total = max(1, int(count.sum()))
        first += (both.sum() + only_first.sum()) / total
        second += (both.sum() + only_second.sum()) / total
    return first / len(blocks.domains), second / len(blocks.domains)


@cache
def _fisher_p(first: int, second: int, sessions: int) -> float:
    p = fisher_success(first, sessions, second, sessions).p_value
    return 1.0 if p is None else p


def _midp(first_only: np.ndarray, second_only: np.ndarray) -> np.ndarray:
    """``mcnemar_midp`` for arrays of counts (SciPy's binomial, vectorised)."""
    from scipy.stats import binom

    n = first_only + second_only
    m = np.minimum(first_only, second_only)
    p = 2 * binom.cdf(m, n, 0.5) - binom.pmf(m, n, 0.5)
    return np.where(n == 0, 1.0, np.minimum(1.0, p))


def simulated_studies(
    blocks: Blocks,
    participants: int,
    studies: int,
    rng: np.random.Generator,
    no_difference: bool = False,
) -> dict[str, np.ndarray]:
    """Per simulated study of ``participants``: the counts of blocks over all environments
    (``both``, ``first_only``, ``second_only``, ``blocks``)."""
    shares = np.bincount(
        np.arange(participants) % len(blocks.domains), minlength=len(blocks.domains)
    )
    totals = {
        key: np.zeros(studies, dtype=np.int64) for key in ("both", "first", "second", "blocks")
    }
    for d, count in enumerate(shares):
        pool = len(blocks.both[d])
        if count == 0 or pool == 0:
            continue
        drawn = rng.integers(pool, size=(studies, int(count)))
        totals["both"] += blocks.both[d][drawn].sum(axis=1)
        totals["first"] += blocks.first_only[d][drawn].sum(axis=1)
        totals["second"] += blocks.second_only[d][drawn].sum(axis=1)
        totals["blocks"] += blocks.blocks[d][drawn].sum(axis=1)
    if no_difference:
        # Each discordant block's two outcomes swapped with probability 1/2.
        discordant = totals["first"] + totals["second"]
        totals["first"] = rng.binomial(discordant, 0.5)
        totals["second"] = discordant - totals["first"]
    return totals


def power_row(
    participants: int,
    test: str,
    rejected: np.ndarray,
    ahead: np.ndarray,
    reached: tuple[float, float],
) -> dict[str, object]:
    studies = len(rejected)
    hits = int((rejected & ahead).sum())
    low, high = wilson(hits, studies)
    return {
        "participants": participants,
        "test": test,
        "studies": studies,
        "power": hits / studies,
        "power_low": low,
        "power_high": high,
        "rejections": float(rejected.mean()),
        "baseline_sessions_reached": reached[0],
        "alternative_sessions_reached": reached[1],
    }


def wilson(hits: int, n: int) -> tuple[float, float]:
    """Wilson's 95% interval for a binomial share."""
    share = hits / n
    centre = (share + Z95**2 / (2 * n)) / (1 + Z95**2 / n)
    half = Z95 * np.sqrt(share * (1 - share) / n + Z95**2 / (4 * n**2)) / (1 + Z95**2 / n)
    return float(max(0.0, centre - half)), float(min(1.0, centre + half))


def power_table(
    blocks: Blocks,
    participants: Sequence[int],
    studies: int,
    seed: int,
    alpha: float = 0.05,
    no_difference: bool = False,
    advance: Callable[[], None] = lambda: None,
) -> pd.DataFrame:
    """``POWER_COLUMNS``, a row per (number of participants, test). The studies at each N
    come from their own stream, (seed, N): adding an N leaves the others' rows as they were."""
    rows: list[dict[str, object]] = []
    for n in participants:
        rng = np.random.default_rng([seed, n])
        totals = simulated_studies(blocks, n, studies, rng, no_difference)
        first = totals["both"] + totals["first"]
        second = totals["both"] + totals["second"]
        sessions = totals["blocks"]
        reached = (
            float(first.mean() / max(1, sessions.mean())),
            float(second.mean() / max(1, sessions.mean())),
        )
        ahead = first > second
        p_mcnemar = _midp(totals["first"], totals["second"])
        rows.append(power_row(n, "mcnemar_midp", p_mcnemar < alpha, ahead, reached))
        p_fisher = np.array(
            [
                _fisher_p(int(a), int(b), int(s))
                for a, b, s in zip(first, second, sessions, strict=True)
            ]
        )
        rows.append(power_row(n, "fisher_exact", p_fisher < alpha, ahead, reached))
        advance()
    return pd.DataFrame(rows, columns=list(POWER_COLUMNS))


def participants_needed(table: pd.DataFrame, test: str, target: float = TARGET) -> int | None:
    """The fewest participants of the table at which ``test``'s power is at least ``target``
    (and stays so at every larger number of the table); None if none."""
    rows = table.loc[table["test"] == test].sort_values("participants")
    enough = (rows["power"] >= target).to_numpy()
    for i in range(len(rows)):
        if enough[i:].all():
            return int(rows["participants"].iloc[i])
    return None
