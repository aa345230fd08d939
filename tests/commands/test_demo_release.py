"""`bam-study demo` writes the study's release beside its CSVs: Croissant, the Frictionless
data package, the Psych-DS folder and the Hugging Face layout, each passing its own validator
with the counts of participants.csv and events.csv, and saying its participants are
simulated."""

from __future__ import annotations

import json

import pytest

from tests.app.export.test_release import (
    check_croissant,
    check_data_package,
    check_parquet,
    check_psych_ds,
    hub_offline,  # noqa: F401  (the fixture: datasets and the Hub offline)
    row_counts,
)
from tests.support.demo import DemoRun


@pytest.mark.slow
def test_the_demo_writes_every_format_of_the_release(small_demo: DemoRun) -> None:
    assert small_demo.code == 0, small_demo.stderr
    export = small_demo.out / "export"
    counts = row_counts(export)
    assert counts["participants"] == 2 and counts["events"] > 0
    check_data_package(export)
    check_croissant(export)
    loaded = check_parquet(export, counts)
    assert loaded["events"].num_rows == counts["events"]
    check_psych_ds(export / "psych-ds", counts)
    croissant = json.loads((export / "croissant.json").read_text())
    assert croissant["rai:dataLimitations"].startswith(
        "Every participant of this dataset is simulated"
    )
    assert "2 participants (2 submitted)" in croissant["rai:dataCollection"]
