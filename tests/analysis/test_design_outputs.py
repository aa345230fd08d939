"""The design-respecting comparisons in the outputs of an analysis of the small study."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from analysis.data import load_tables
from analysis.design_results import DESIGN_COLUMNS
from analysis.report import describe_outputs, write_outputs
from analysis.results import analyze

from .conftest import small_study, write_export


def read_rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="", encoding="utf-8") as file:
        return list(csv.DictReader(file))


def test_the_design_outputs(tmp_path: Path) -> None:
    notes: list[str] = []
    sessions, evaluations = load_tables(write_export(tmp_path / "e", small_study()), notes=notes)
    analysis = analyze(sessions, evaluations, notes=notes)
    names = write_outputs(analysis, tmp_path / "out")
    out = tmp_path / "out"
    assert {"design.md", "design_comparisons.csv", "survival_episodes.svg"} <= set(names)
    with (out / "design_comparisons.csv").open(newline="", encoding="utf-8") as file:
        assert next(csv.reader(file)) == list(DESIGN_COLUMNS)
    rows = read_rows(out / "design_comparisons.csv")
    # 3 scopes x 2 thresholds x 2 alternatives x (McNemar, GEE, Cox episodes, Cox actions)
    assert len(rows) == 3 * 2 * 2 * 4
    key = {(r["scope"], r["test"], r["measure"], r["threshold"], r["alternative"]): r for r in rows}
    row = key[("two-rooms", "mcnemar_midp", "success", "0.8", "cloning")]
    # Every participant's BAM session reached 80% in Two Rooms, no Cloning session did: 4
    # discordant blocks one way, mid-p 2 * (1/16) - 1/16.
    assert (row["blocks"], row["baseline_only"], row["alternative_only"]) == ("4", "4", "0")
    assert float(row["p_value"]) == pytest.approx(1 / 16)
    assert float(row["risk_difference"]) == -1.0
    assert row["p_adjusted"] and row["sentence"].startswith(
        "Behavioral Cloning against BAM in Two Rooms, success at 80%"
    )
    pooled = key[("all", "mcnemar_midp", "success", "0.8", "cloning")]
    assert pooled["blocks"] == "8" and pooled["p_adjusted"] == ""
    assert float(pooled["p_value"]) == pytest.approx(2 / 256 - 1 / 256)
    # Within-block separation is said, not fitted.
    cox = key[("two-rooms", "cox_stratified", "episodes", "0.5", "model-based")]
    assert cox["p_value"] == "" and "not estimable" in cox["note"]
    # The family: environment-specific McNemar and Cox p-values.
    family = [r for r in rows if r["p_adjusted"]]
    assert all(r["scope"] != "all" and r["test"] != "gee_logistic" for r in family)
    assert f"the {len(family)} environment-specific" in (out / "design.md").read_text()

    omnibus = read_rows(out / "design_omnibus.csv")
    assert len(omnibus) == 3 * 2
    medians = read_rows(out / "survival_medians.csv")
    bam = [m for m in medians if m["scope"] == "two-rooms" and m["learner"] == "bam"]
    # BAM reaches 80% in Two Rooms after 3, 3, 4 and 4 episodes: the estimate is 1/2 from 3 and
    # falls below it at 4, the median (the first count where it is below 1/2).
    episodes_80 = next(m for m in bam if m["measure"] == "episodes" and m["threshold"] == "0.8")
    assert (episodes_80["reached"], episodes_80["median"]) == ("4", "4.0")

    readme = describe_outputs(analysis)
    section = readme.index("## Comparisons within participants")
    assert section < readme.index("## Notes on this study's data")
    assert "`design_comparisons.csv`" in readme
