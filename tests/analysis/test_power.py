"""Power by resampling participants from a bank of sessions (``analysis.power``): the same
seed gives the same table; with no true difference the power is the test's level; with a
clear difference it grows with the participants; the vectorised McNemar and the sessions'
traits match what they stand for."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from analysis.design import mcnemar_midp
from analysis.power import (
    _midp,
    bank_blocks,
    participants_needed,
    power_table,
    simulated_studies,
)
from analysis.power_bank import Population, draw_traits, first_reached

ALPHA = 0.05
REACHED = [[0, 0, 0.1], [1, 9, 0.9]]
MISSED = [[0, 0, 0.1], [1, 9, 0.5]]
DOMAINS = {"navigation": ("two-rooms", "doorway"), "farming": ("two-fields", "three-fields")}


def synthetic_bank(
    chance: dict[str, float], participants: int, seed: int, skill_spread: float = 2.0
) -> pd.DataFrame:
    """Sessions of bam and cloning: a participant's skill (on the logit scale, widely spread
    and shared by all their sessions) plus the learner's effect decides whether each session
    reaches 0.8."""
    rng = np.random.default_rng(seed)
    rows = []
    for domain, environments in DOMAINS.items():
        for participant in range(participants):
            skill = rng.normal(0, skill_spread)
            for environment in environments:
                for learner, base in chance.items():
                    logit = np.log(base / (1 - base)) + skill
                    reached = rng.random() < 1 / (1 + np.exp(-logit))
                    rows.append(
                        {
                            "domain": domain,
                            "participant": participant,
                            "environment": environment,
                            "learner": learner,
                            "curve": REACHED if reached else MISSED,
                        }
                    )
    return pd.DataFrame(rows)


def level_margin(studies: int) -> float:
    """Three binomial standard errors of a rejection rate at the level."""
    return float(3 * np.sqrt(ALPHA * (1 - ALPHA) / studies))


def test_the_same_seed_gives_the_same_table_and_another_seed_another() -> None:
    bank = synthetic_bank({"bam": 0.6, "cloning": 0.4}, 12, seed=1)
    blocks = bank_blocks(bank, "bam", "cloning", 0.8)
    first = power_table(blocks, [4, 8], 300, seed=7)
    again = power_table(blocks, [4, 8], 300, seed=7)
    pd.testing.assert_frame_equal(first, again)
    other = power_table(blocks, [4, 8], 300, seed=8)
    assert not first["power"].equals(other["power"])
    # Each number of participants has its own stream: adding one leaves the others alone.
    more = power_table(blocks, [4, 6, 8], 300, seed=7)
    pd.testing.assert_frame_equal(more.loc[more["participants"] != 6].reset_index(drop=True), first)


def mirrored(bank: pd.DataFrame) -> pd.DataFrame:
    """The bank and its mirror image, the learners' outcomes swapped (participants renumbered
    after the bank's): both learners draw from the same outcomes, block by block."""
    mirror = bank.assign(
        participant=bank["participant"] + bank["participant"].max() + 1,
        learner=bank["learner"].map({"bam": "cloning", "cloning": "bam"}),
    )
    return pd.concat([bank, mirror], ignore_index=True)


def test_with_no_true_difference_the_power_is_the_tests_level() -> None:
    # Participants differ widely in skill; in a bank drawn at random the two learners'
    # shares differ by chance, and resampling would take that for a difference: the mirror
    # makes them draw from the same outcomes. (A small bank also holds, by chance, more
    # participants whose two blocks favour the same learner than the population does, which
    # the McNemar test does not expect: 300 participants a domain keep that small.)
    bank = mirrored(synthetic_bank({"bam": 0.5, "cloning": 0.5}, 300, seed=2))
    blocks = bank_blocks(bank, "bam", "cloning", 0.8)
    studies = 4000
    table = power_table(blocks, [40], studies, seed=3, alpha=ALPHA)
    margin = level_margin(studies)
    for row in table.itertuples():
        # Either direction: at most the level; with the first learner ahead: half of it.
        assert row.rejections < ALPHA + margin, table
        assert row.power < ALPHA / 2 + margin, table
    by = table.set_index("test")["rejections"]
    # The design's test is near its level (its size moves with the bank: 0.037 to 0.052
    # over three seeds of the bank); the pooled Fisher test, blind to the pairing of a
    # block's sessions by the teacher's skill, far below it (its power is wasted).
    assert by["mcnemar_midp"] > 0.6 * ALPHA, table
    assert by["fisher_exact"] < by["mcnemar_midp"] / 2, table
    assert table["baseline_sessions_reached"].iloc[0] == pytest.approx(
        table["alternative_sessions_reached"].iloc[0], abs=0.02
    )


def test_swapping_outcomes_within_blocks_gives_the_level_on_a_bank_with_a_difference() -> None:
    bank = synthetic_bank({"bam": 0.7, "cloning": 0.3}, 40, seed=4)
    blocks = bank_blocks(bank, "bam", "cloning", 0.8)
    studies = 4000
    real = power_table(blocks, [24], studies, seed=5)
    swapped = power_table(blocks, [24], studies, seed=5, no_difference=True)
    mcnemar = swapped.set_index("test").loc["mcnemar_midp"]
    assert mcnemar["rejections"] < ALPHA + level_margin(studies), swapped
    assert mcnemar["rejections"] > ALPHA / 2, swapped  # the mid-p is not very conservative
    assert real.set_index("test").loc["mcnemar_midp", "power"] > 0.5, real


def test_power_grows_with_participants_when_one_learner_is_clearly_better() -> None:
    bank = synthetic_bank({"bam": 0.8, "cloning": 0.2}, 40, seed=6)
    blocks = bank_blocks(bank, "bam", "cloning", 0.8)
    studies = 2000
    sizes = [2, 4, 8, 16, 32, 48]
    table = power_table(blocks, sizes, studies, seed=9)
    noise = 3 * np.sqrt(0.25 / studies)
    for test in ("mcnemar_midp", "fisher_exact"):
        power = table.loc[table["test"] == test, "power"].to_numpy()
        assert (np.diff(power) > -noise).all(), table
        assert power[0] < 0.3 and power[-1] > 0.8, table
        needed = participants_needed(table, test)
        assert needed is not None and needed > 4
        assert (
            table.loc[(table["test"] == test) & (table["participants"] >= needed), "power"] >= 0.8
        ).all()
    # The design's test is at least as powerful as pooling the sessions (paired data).
    by = table.set_index(["participants", "test"])["power"]
    assert all(by[(n, "mcnemar_midp")] >= by[(n, "fisher_exact")] - noise for n in sizes)


def test_participants_needed_is_none_when_the_target_is_never_reached() -> None:
    table = pd.DataFrame(
        {"participants": [4, 8, 12], "test": ["mcnemar_midp"] * 3, "power": [0.5, 0.82, 0.79]}
    )
    assert participants_needed(table, "mcnemar_midp") is None
    table.loc[2, "power"] = 0.9
    assert participants_needed(table, "mcnemar_midp") == 8


def test_studies_assign_participants_to_domains_in_turn_and_keep_their_blocks_together() -> None:
    bank = synthetic_bank({"bam": 0.6, "cloning": 0.4}, 10, seed=10)
    blocks = bank_blocks(bank, "bam", "cloning", 0.8)
    assert blocks.domains == ("navigation", "farming")
    # Every participant brings both environments of their domain as blocks.
    assert all((b == 2).all() for b in blocks.blocks)
    totals = simulated_studies(blocks, 5, 50, np.random.default_rng(0))
    assert (totals["blocks"] == 10).all()  # 3 + 2 participants, 2 blocks each
    assert (totals["both"] + totals["first"] + totals["second"] <= totals["blocks"]).all()


def test_the_vectorised_mcnemar_is_the_analysis_s() -> None:
    first = np.array([0, 3, 7, 10, 2, 0])
    second = np.array([0, 1, 7, 2, 9, 5])
    expected = [mcnemar_midp(int(a), int(b)) for a, b in zip(first, second, strict=True)]
    assert _midp(first, second) == pytest.approx(expected, abs=1e-12)


def test_a_participant_s_traits_are_drawn_once_from_the_population() -> None:
    population = Population()
    same = draw_traits(population, 0, 1, 5)
    assert same == draw_traits(population, 0, 1, 5)
    traits = [draw_traits(population, 0, 0, p) for p in range(400)]
    mistakes = np.array([t.mistake_probability for t in traits])
    alphas = np.array([t.feedback_alpha for t in traits])
    assert abs(mistakes.mean() - population.mistake_mean) < 0.02
    assert abs(np.median(np.log(alphas))) < 0.2  # the paper's alpha, 1, is the median
    assert {t.rounds for t in traits} == {3, 4, 5}


def test_first_reached_is_the_first_evaluation_at_or_above_the_threshold() -> None:
    curve = [[0, 0, 0.2], [1, 6, 0.8], [2, 11, 0.95]]
    assert first_reached(curve, 0.8) == (1, 6)
    assert first_reached(curve, 0.9) == (2, 11)
    assert first_reached(curve, 0.99) is None


def test_the_learners_of_a_block_are_taught_alike_and_a_participant_s_traits_are_kept() -> None:
    """One participant's two sessions in an environment: the same traits, the same
    demonstrations from the same starts and the same choice of agent tries (so the same
    episodes after every update); the learners' own moves differ. Another participant differs."""
    from analysis.power_bank import BankPlan, simulate_session

    plan = BankPlan(
        domains=(("navigation", ("two-rooms",)),),
        learners=("bam", "cloning"),
        participants=2,
        seed=0,
        population=Population(rounds=(1, 1)),
    )
    first, second, other, _ = plan.jobs()
    assert first.traits == second.traits != other.traits
    rows = [simulate_session(job) for job in (first, second, other)]
    episodes = [[point[0] for point in row["curve"]] for row in rows]
    assert episodes[0] == episodes[1]
    assert rows[0]["curve"] != rows[1]["curve"]
    assert simulate_session(first) == rows[0]  # the same streams, the same session
