"""``bam-study power`` end to end on the paper's study, at a size that runs in seconds: it
prints the power table and the answer, writes the table and the figure, reuses its bank, and
refuses bad input with a message and exit status 2 before simulating anything."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from analysis.power import POWER_COLUMNS
from server.commands.main import main

SMALL = ["--bank", "1", "--rounds", "1", "--studies", "50", "--participants", "2,4", "--jobs", "1"]


def power(capsys: pytest.CaptureFixture[str], *args: str | Path) -> tuple[int, str, str]:
    try:
        code = main(["power", *(str(a) for a in args)])
    except SystemExit as stop:  # argparse's errors
        code = int(stop.code or 0)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_power_prints_the_table_and_the_answer_and_reuses_its_bank(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "power"
    code, printed, err = power(
        capsys, "--compare", "bam", "cloning", "--threshold", "0.8", *SMALL, "--out", out
    )
    assert code == 0, err
    assert "Power to see BAM beat Behavioral Cloning at 80%" in printed
    assert "In the bank, BAM reached 80% in " in printed
    answer = printed.strip().splitlines()[-1]
    assert answer.startswith(
        "80% power to see BAM beat Behavioral Cloning at 80% (exact McNemar mid-p, alpha 0.05):"
    ), printed
    assert "8/8 sessions" in err  # 2 domains x 2 environments x 2 learners, 1 participant
    with (out / "power.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert tuple(rows[0]) == POWER_COLUMNS
    assert [(r["participants"], r["test"]) for r in rows] == [
        ("2", "mcnemar_midp"),
        ("2", "fisher_exact"),
        ("4", "mcnemar_midp"),
        ("4", "fisher_exact"),
    ]
    assert all(0 <= float(r["power"]) <= float(r["rejections"]) <= 1 for r in rows)
    for name in ("power.png", "power.svg", "power_bank.json", "power_bank.jsonl"):
        assert (out / name).stat().st_size > 0, name
    # With two participants (four blocks) the exact McNemar cannot reject at 0.05: its
    # smallest mid-p is 2/16 - 1/16.
    assert float(rows[0]["power"]) == 0.0

    table = (out / "power.csv").read_text()
    code, again, err = power(
        capsys, "--compare", "bam", "cloning", "--threshold", "0.8", *SMALL, "--out", out
    )
    assert code == 0, err
    assert "resuming: 8 of 8 sessions already done" in err
    assert again == printed
    assert (out / "power.csv").read_text() == table

    # A new folder simulates the bank again, to the same sessions and the same table.
    fresh = tmp_path / "fresh"
    code, anew, err = power(capsys, *SMALL, "--out", fresh)
    assert code == 0, err
    assert anew == printed
    assert sorted((fresh / "power_bank.jsonl").read_text().splitlines()) == sorted(
        (out / "power_bank.jsonl").read_text().splitlines()
    )

    # Another pair of the study's learners reuses the sessions of the learner they share.
    code, _, err = power(capsys, "--compare", "bam", "model-based", *SMALL, "--out", out)
    assert code == 0, err
    assert "resuming: 4 of 8 sessions already done" in err

    # Another seed is another bank: not in this folder.
    code, _, err = power(capsys, *SMALL, "--seed", "1", "--out", out)
    assert code == 2
    assert "holds a bank simulated with other arguments (seed differ)" in err


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--compare", "bam", "global-cost"], "'global-cost' is not a learner of the study"),
        (["--compare", "bam", "bam"], "give two different learners"),
        (["--threshold", "0.7"], "--threshold 0.7 is not one of the study's thresholds (0.5, 0.8)"),
        (["--thresholds", "0.5,1.5"], "1.5 is outside (0, 1]"),
        (["--participants", "0,4"], "each number of participants at least 1"),
        (["--participants", "four"], "give whole numbers separated by commas"),
        (["--studies", "0"], "--studies must be at least 1"),
        (["--bank", "0"], "--bank must be at least 1"),
        (["--alpha", "1.5"], "--alpha must be in (0, 1)"),
        (["--rounds", "3-1"], "give N or N-M with 1 <= N <= M"),
        (["--study", "no-such-study.toml"], "no-such-study.toml"),
    ],
)
def test_bad_input_is_refused_with_a_message_before_anything_is_simulated(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], arguments: list[str], message: str
) -> None:
    out = tmp_path / "power"
    code, printed, err = power(capsys, *arguments, "--out", out)
    assert code == 2
    assert message in err, err
    assert printed == ""
    assert not out.exists()
