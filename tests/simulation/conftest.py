"""A small simulated-teacher run shared by the tests: two small environments, two agents, two
rounds and learner settings that cut the optimisation to a few steps."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from server.commands.main import main

ENVIRONMENTS = ("wall", "doorway")
AGENTS = 2
ROUNDS = 2
FAST_SETTINGS = ("alternations=2", "cost_steps=5", "dynamics_steps=5", "steps=20")
# Columns that hold measured time: they differ between any two runs.
TIMING_COLUMNS = ("update_seconds", "mean_update_seconds")


def small_args(out: Path, experiment: str = "feedback", *extra: str) -> list[str]:
    args = [
        "simulate",
        "--experiment",
        experiment,
        "--environments",
        *ENVIRONMENTS,
        "--agents",
        str(AGENTS),
        "--rounds",
        str(ROUNDS),
        "--seed",
        "7",
        "--out",
        str(out),
    ]
    for setting in FAST_SETTINGS:
        args += ["--learner-setting", setting]
    return [*args, *extra]


def read_csv(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    with path.open(newline="", encoding="utf-8") as handle:
        reader = csv.DictReader(handle)
        return list(reader.fieldnames or []), list(reader)


def without_timing(path: Path) -> list[dict[str, str]]:
    """The CSV's rows without the measured-time columns (everything else must be identical)."""
    _, rows = read_csv(path)
    return [{k: v for k, v in row.items() if k not in TIMING_COLUMNS} for row in rows]


@pytest.fixture(scope="session")
def small_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The feedback experiment (the protocol with every step) run uninterrupted, one job at a
    time."""
    out = tmp_path_factory.mktemp("simulation") / "run"
    assert main(small_args(out, "feedback", "--jobs", "1")) == 0
    return out
