"""`bam-study analyze` end to end: its outputs, and every kind of bad input (exit code, a
message naming the file, row and column, and nothing written)."""

from __future__ import annotations

import csv
import subprocess
import sys
import xml.etree.ElementTree as ElementTree
from collections.abc import Callable
from pathlib import Path

import pytest

from analysis.stats import COMPARISON_COLUMNS
from server.commands.main import main

from .conftest import small_study, write_export

OUTPUTS = {
    "README.md",
    "appendix_all.md",
    "appendix_all.tex",
    "appendix_raw.md",
    "appendix_raw.tex",
    "comparisons.csv",
    "design.md",
    "design_comparisons.csv",
    "design_omnibus.csv",
    "participant_flow.csv",
    "participant_flow.png",
    "participant_flow.svg",
    "return_vs_actions.png",
    "return_vs_actions.svg",
    "return_vs_episodes.png",
    "return_vs_episodes.svg",
    "sessions_summary.csv",
    "survival_actions.png",
    "survival_actions.svg",
    "survival_episodes.png",
    "survival_episodes.svg",
    "survival_medians.csv",
    "table1.md",
    "table1.tex",
}


def analyze(capsys: pytest.CaptureFixture[str], *args: str | Path) -> tuple[int, str, str]:
    try:
        code = main(["analyze", *(str(a) for a in args)])
    except SystemExit as exit:  # argparse rejects an argument
        code = int(exit.code or 0)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def read_rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="", encoding="utf-8") as file:
        return list(csv.DictReader(file))


def rewrite(path: Path, rows: list[dict[str, str]], columns: list[str] | None = None) -> None:
    columns = columns or list(rows[0])
    with path.open("w", newline="", encoding="utf-8") as file:
        writer = csv.DictWriter(file, fieldnames=columns, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)


def set_cell(name: str, row: int, column: str, value: str) -> Callable[[Path], None]:
    """Set a cell of an export file (``row`` counts data rows from 1, like the messages)."""

    def edit(folder: Path) -> None:
        rows = read_rows(folder / name)
        rows[row - 1][column] = value
        rewrite(folder / name, rows)

    return edit


def drop_column(name: str, column: str) -> Callable[[Path], None]:
    def edit(folder: Path) -> None:
        rows = read_rows(folder / name)
        rewrite(folder / name, rows, [c for c in rows[0] if c != column])

    return edit


def remove(name: str) -> Callable[[Path], None]:
    return lambda folder: (folder / name).unlink()


def header_only(name: str) -> Callable[[Path], None]:
    def edit(folder: Path) -> None:
        header = (folder / name).read_text(encoding="utf-8").splitlines()[0]
        (folder / name).write_text(header + "\n", encoding="utf-8")

    return edit


def append_line(name: str, line: str) -> Callable[[Path], None]:
    def edit(folder: Path) -> None:
        with (folder / name).open("a", encoding="utf-8") as file:
            file.write(line + "\n")

    return edit


# --- The outputs ----------------------------------------------------------------------------


def test_analyze_writes_every_output_and_prints_table1(
    export: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "results" / "run1"  # parents are created
    code, stdout, stderr = analyze(capsys, "--data", export, "--out", out)
    assert (code, stderr) == (0, "")
    assert {p.name for p in out.iterdir()} == OUTPUTS
    table1 = (out / "table1.md").read_text(encoding="utf-8")
    assert stdout.startswith(table1)
    assert "24 learning sessions of 4 participants in 2 environments; 1 without evaluations." in (
        stdout
    )
    assert f"Results written to {out}" in stdout

    with (out / "comparisons.csv").open(newline="", encoding="utf-8") as file:
        reader = csv.reader(file)
        assert next(reader) == list(COMPARISON_COLUMNS)  # the required ones, then note
    comparisons = read_rows(out / "comparisons.csv")
    # 2 environments + all, x 3 measures x 2 thresholds x 2 alternatives
    assert len(comparisons) == 3 * 3 * 2 * 2
    assert {row["scope"] for row in comparisons} == {"two-rooms", "doorway", "all"}
    assert {row["threshold"] for row in comparisons} == {"0.5", "0.8"}
    for row in comparisons:
        if row["scope"] == "all":
            assert row["p_adjusted"] == "" and row["significant_adjusted"] == ""
        if row["test"] == "N/A":
            assert row["p_value"] == "" and row["note"]
    by_key = {(r["scope"], r["measure"], r["threshold"], r["alternative"]): r for r in comparisons}
    row = by_key[("two-rooms", "success", "0.8", "cloning")]
    assert (row["baseline_value"], row["alternative_value"]) == ("4", "0")
    assert float(row["p_value"]) == pytest.approx(2 / 70)
    assert row["significant"] == "True"
    row = by_key[("doorway", "episodes", "0.8", "model-based")]
    assert row["test"] == "N/A"
    assert "1 Model-Based IRL sessions in Doorway reached 80%" in row["note"]
    row = by_key[("all", "episodes", "0.8", "cloning")]
    assert row["test"] == "N/A" and "too few sessions for an ANOVA" in row["note"]
    assert by_key[("all", "episodes", "0.5", "cloning")]["test"] == "anova_type2"

    summary = read_rows(out / "sessions_summary.csv")
    assert len(summary) == 24
    first = summary[0]
    assert (first["session_id"], first["reached_80"], first["episodes_80"]) == ("s01", "True", "3")
    assert (first["actions_50"], first["actions_80"]) == ("24", "39")
    no_evaluations = [r for r in summary if r["evaluations"] == "0"]
    assert len(no_evaluations) == 1 and no_evaluations[0]["episodes_50"] == ""

    for name in ("return_vs_episodes", "return_vs_actions"):
        assert (out / f"{name}.png").read_bytes().startswith(b"\x89PNG\r\n\x1a\n")
        root = ElementTree.parse(out / f"{name}.svg").getroot()
        assert root.tag.endswith("svg")
    assert not list(out.parent.glob(".*partial"))


def test_options_reach_the_outputs(
    export: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    code, stdout, _ = analyze(
        capsys,
        "--data",
        export,
        "--out",
        out,
        "--thresholds",
        "0.9, 0.3",
        "--fdr",
        "0.05",
        "--baseline",
        "cloning",
    )
    assert code == 0
    assert "Successful 30% | Successful 90%" in stdout
    assert "significantly worse than Behavioral Cloning" in stdout
    # The legend names the rate only beside a mark that uses it (Table 1's legend defines only
    # the marks its cells use); the outputs' README always states it.
    readme = (out / "README.md").read_text(encoding="utf-8")
    assert "False discovery rate of the Benjamini-Yekutieli correction: 0.05." in readme
    if "†" in stdout:
        assert "at a false discovery rate of 5%" in stdout
    comparisons = read_rows(out / "comparisons.csv")
    assert {row["threshold"] for row in comparisons} == {"0.3", "0.9"}
    assert {row["baseline"] for row in comparisons} == {"cloning"}


def test_a_second_run_replaces_the_outputs(
    export: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "table1.md").write_text("stale", encoding="utf-8")
    (out / "mine.txt").write_text("kept", encoding="utf-8")
    assert analyze(capsys, "--data", export, "--out", out)[0] == 0
    assert (out / "table1.md").read_text(encoding="utf-8").startswith("|")
    assert (out / "mine.txt").read_text(encoding="utf-8") == "kept"


def test_exclude_excluded(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    export = write_export(tmp_path / "export", small_study(), excluded={"p1"})
    code, stdout, _ = analyze(
        capsys, "--data", export, "--out", tmp_path / "out", "--exclude-excluded"
    )
    assert code == 0
    assert "excluded 6 learning sessions of 1 participant marked excluded" in stdout
    assert "18 learning sessions of 3 participants" in stdout
    assert len(read_rows(tmp_path / "out" / "sessions_summary.csv")) == 18


def test_exclude_flagged(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Participants a chosen quality check flags are left out, and only those."""
    export = write_export(tmp_path / "export", small_study())
    (export / "quality.csv").write_text(
        "participant_id,flags\np1,poor_demonstrations inconsistent_feedback\np2,long_idle\np3,\n",
        encoding="utf-8",
    )
    code, stdout, _ = analyze(
        capsys,
        "--data",
        export,
        "--out",
        tmp_path / "out",
        "--exclude-flagged",
        "poor_demonstrations,exceptionally_fast",
    )
    assert code == 0
    assert (
        "excluded 6 learning sessions of 1 participant flagged poor_demonstrations or "
        "exceptionally_fast in quality.csv"
    ) in stdout
    kept = {row["participant_id"] for row in read_rows(tmp_path / "out" / "sessions_summary.csv")}
    assert "p1" not in kept and {"p2", "p3"} <= kept


@pytest.mark.parametrize(
    ("flags", "quality", "message"),
    [
        ("careless", "participant_id,flags\n", "'careless' is not a quality check; choose from"),
        ("long_idle", None, "--exclude-flagged needs quality.csv, which is not in"),
        (
            "long_idle",
            "participant,flag\np1,long_idle\n",
            "quality.csv: --exclude-flagged needs the columns 'participant_id' and 'flags'",
        ),
    ],
)
def test_exclude_flagged_refuses_what_it_cannot_do(
    flags: str,
    quality: str | None,
    message: str,
    export: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    if quality is not None:
        (export / "quality.csv").write_text(quality, encoding="utf-8")
    out = tmp_path / "out"
    code, _, stderr = analyze(capsys, "--data", export, "--out", out, "--exclude-flagged", flags)
    assert code == 2
    assert message in stderr
    assert not out.exists()


def test_exclude_flagged_names_every_check_of_the_quality_table(
    capsys: pytest.CaptureFixture[str],
) -> None:
    from server.app.export.quality import FLAGS
    from server.commands.main import main

    with pytest.raises(SystemExit):
        main(["analyze", "--help"])
    shown = " ".join(capsys.readouterr().out.split())
    assert all(flag in shown.split("--exclude-flagged", 2)[2] for flag in FLAGS), shown


def notes_under(text: str, heading: str) -> list[str]:
    """The ``- `` items after ``heading`` (a line of the text), up to the next heading."""
    lines = text.split(heading, 1)[1].splitlines()
    items = []
    for line in lines[1:]:
        if line.startswith("#"):
            break
        if line.startswith("- "):
            items.append(line[2:])
    return items


def test_sessions_of_participants_who_did_not_finish_are_left_out_unless_asked_for(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The fourth participant returned the task after teaching five of six agents."""
    statuses = {"p1": "submitted", "p2": "completed", "p3": "submitted", "p4": "returned"}
    export = write_export(tmp_path / "export", small_study(), participants=statuses)
    note = (
        "left out 6 learning sessions of 1 participant who did not complete the study "
        "(returned the task: 6); 1 never taught (no episode or action); --include-unfinished adds "
        "the 5 taught"
    )
    out = tmp_path / "out"
    code, stdout, stderr = analyze(capsys, "--data", export, "--out", out)
    assert (code, stderr) == (0, "")
    assert "18 learning sessions of 3 participants in 2 environments" in stdout
    assert f"- {note}" in stdout
    assert len(read_rows(out / "sessions_summary.csv")) == 18
    table1 = (out / "table1.md").read_text(encoding="utf-8")
    assert "| Behavioral Cloning |              3 |" in table1  # was 4 in each environment
    readme = (out / "README.md").read_text(encoding="utf-8")
    assert notes_under(readme, "## Notes on this study's data") == [note]
    assert "Learning sessions counted: those of the participants who completed the study" in (
        readme
    )

    out = tmp_path / "with-unfinished"
    code, stdout, _ = analyze(capsys, "--data", export, "--out", out, "--include-unfinished")
    assert code == 0
    assert "23 learning sessions of 4 participants in 2 environments; 0 without" in stdout
    assert (
        "- --include-unfinished: counted 5 taught learning sessions of 1 participant who did "
        "not complete the study (returned the task: 5)"
    ) in stdout
    assert "- left out 1 learning session never taught (no episode or action)" in stdout


def test_the_readme_gives_the_notes_there_are_and_no_other(
    export: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The outputs' README promises no note that Table 1 does not have (such as a count of
    empty episodes where there are none): it lists Table 1's notes, or says there are none."""
    out = tmp_path / "out"
    assert analyze(capsys, "--data", export, "--out", out)[0] == 0
    table_notes = notes_under((out / "table1.md").read_text(encoding="utf-8"), "Marks:")
    readme = (out / "README.md").read_text(encoding="utf-8")
    assert table_notes == [
        "1 learning session had no evaluations; it counts in the total "
        "sessions and reached no threshold"
    ]
    assert notes_under(readme, "## Notes on this study's data") == table_notes

    # A study that needs no note: every session taught, episodes.csv without empty episodes.
    whole = [s for s in small_study() if s[5]]
    out = tmp_path / "out2"
    assert analyze(capsys, "--data", write_export(tmp_path / "e2", whole), "--out", out)[0] == 0
    assert notes_under((out / "table1.md").read_text(encoding="utf-8"), "Marks:") == []
    readme = (out / "README.md").read_text(encoding="utf-8")
    assert notes_under(readme, "## Notes on this study's data") == []
    assert readme.rstrip().endswith(
        "None: every learning session counted is of a participant who completed the study "
        "and has evaluations, and `episodes.csv` holds no empty episode."
    )


def test_a_failure_while_writing_leaves_nothing(
    export: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch
) -> None:
    def broken(analysis, folder: Path) -> list[Path]:
        (folder / "return_vs_episodes.png").write_bytes(b"half")
        raise OSError("disk full")

    monkeypatch.setattr("analysis.report.save_learning_curves", broken)
    out = tmp_path / "new" / "out"
    code, _, stderr = analyze(capsys, "--data", export, "--out", out)
    assert code == 1
    assert "disk full" in stderr
    assert not (tmp_path / "new").exists()

    existing = tmp_path / "existing"
    existing.mkdir()
    (existing / "table1.md").write_text("previous", encoding="utf-8")
    assert analyze(capsys, "--data", export, "--out", existing)[0] == 1
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith("partial")] == []
    assert [p.name for p in existing.iterdir()] == ["table1.md"]
    assert (existing / "table1.md").read_text(encoding="utf-8") == "previous"


# --- Bad input ------------------------------------------------------------------------------

# The small study's first evaluations are session s01's (BAM, Two Rooms, participant p1):
# rows 1-5, updates 0-4, episodes 1-5, actions 11, 24, 39, 56, 75.
BAD_DATA = {
    "non-numeric return": (
        set_cell("evaluations.csv", 5, "normalized_return", "abc"),
        "evaluations.csv, row 5 (line 6), column 'normalized_return': 'abc' is not a number",
    ),
    "missing return": (
        set_cell("evaluations.csv", 3, "normalized_return", ""),
        "evaluations.csv, row 3 (line 4), column 'normalized_return': missing value",
    ),
    "return above one": (
        set_cell("evaluations.csv", 2, "normalized_return", "1.2"),
        "evaluations.csv, row 2 (line 3), column 'normalized_return': 1.2 is outside [0, 1]",
    ),
    "negative return": (
        set_cell("evaluations.csv", 4, "normalized_return", "-0.1"),
        "evaluations.csv, row 4 (line 5), column 'normalized_return': -0.1 is outside [0, 1]",
    ),
    "fractional episodes": (
        set_cell("evaluations.csv", 2, "episodes", "2.5"),
        "evaluations.csv, row 2 (line 3), column 'episodes': 2.5 is not a whole number",
    ),
    "missing actions": (
        set_cell("evaluations.csv", 7, "actions", " "),
        "evaluations.csv, row 7 (line 8), column 'actions': missing value",
    ),
    "decreasing episodes": (
        set_cell("evaluations.csv", 3, "episodes", "1"),
        "evaluations.csv, row 3 (line 4), column 'episodes': 1 at update 2 of learning "
        "session 's01' is less than 2 at update 1",
    ),
    "decreasing actions": (
        set_cell("evaluations.csv", 4, "actions", "30"),
        "evaluations.csv, row 4 (line 5), column 'actions': 30 at update 3 of learning "
        "session 's01' is less than 39 at update 2",
    ),
    "duplicate update": (
        set_cell("evaluations.csv", 2, "update_index", "0"),
        "evaluations.csv, row 2 (line 3), column 'update_index': update 0 of learning "
        "session 's01' appears twice",
    ),
    "unknown session": (
        set_cell("evaluations.csv", 6, "session_id", "s99"),
        "evaluations.csv, row 6 (line 7), column 'session_id': learning session 's99' is "
        "not in sessions.csv",
    ),
    "evaluation disagrees with its session": (
        set_cell("evaluations.csv", 1, "learner", "cloning"),
        "evaluations.csv, row 1 (line 2), column 'learner': 'cloning' differs from 'bam'",
    ),
    "unknown learner in evaluations": (
        set_cell("evaluations.csv", 2, "learner", "dagger"),
        "evaluations.csv, row 2 (line 3), column 'learner': unknown learner 'dagger'",
    ),
    "unknown learner": (
        set_cell("sessions.csv", 2, "learner", "dagger"),
        "sessions.csv, row 2 (line 3), column 'learner': unknown learner 'dagger' (known: "
        "bam, model-based, global-cost, cloning)",
    ),
    "non-numeric position": (
        set_cell("sessions.csv", 4, "position", "first"),
        "sessions.csv, row 4 (line 5), column 'position': 'first' is not a number",
    ),
    "bad completed flag": (
        set_cell("sessions.csv", 1, "completed", "maybe"),
        "sessions.csv, row 1 (line 2), column 'completed': 'maybe' is not true or false",
    ),
    "missing session id": (
        set_cell("sessions.csv", 3, "session_id", ""),
        "sessions.csv, row 3 (line 4), column 'session_id': missing value",
    ),
    "duplicate session": (
        set_cell("sessions.csv", 2, "session_id", "s01"),
        "sessions.csv, row 2 (line 3), column 'session_id': learning session 's01' appears "
        "again (first at sessions.csv, row 1 (line 2))",
    ),
    "missing evaluation column": (
        drop_column("evaluations.csv", "actions"),
        "evaluations.csv: missing column(s) 'actions'",
    ),
    "missing session columns": (
        drop_column("sessions.csv", "position"),
        "sessions.csv: missing column(s) 'position'",
    ),
    "missing evaluations file": (remove("evaluations.csv"), "evaluations.csv not found in"),
    "missing sessions file": (remove("sessions.csv"), "sessions.csv not found in"),
    "no sessions": (header_only("sessions.csv"), "sessions.csv: no learning sessions"),
    "a row with too many fields": (
        append_line("evaluations.csv", "s01,p1,navigation,two-rooms,bam,0,9,9,99,0.5,extra"),
        "evaluations.csv: not a readable CSV file: Error tokenizing data. C error: Expected "
        "10 fields in line 169, saw 11",
    ),
}


@pytest.mark.parametrize("case", list(BAD_DATA))
def test_bad_data_is_rejected_with_where_and_nothing_written(
    case: str, export: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    edit, message = BAD_DATA[case]
    edit(export)
    out = tmp_path / "out"
    code, stdout, stderr = analyze(capsys, "--data", export, "--out", out)
    assert code == 2
    assert stderr.startswith("bam-study analyze: error: ")
    assert message in stderr
    assert stderr.count("\n") == 1  # one line
    assert stdout == ""
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["export"]


def test_a_missing_export_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, stderr = analyze(capsys, "--data", tmp_path / "nowhere", "--out", tmp_path / "o")
    assert code == 2
    assert f"bam-study analyze: error: export folder {tmp_path / 'nowhere'} does not exist" in (
        stderr
    )
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--thresholds", "0"], "argument --thresholds: 0 is outside (0, 1]"),
        (["--thresholds", "1.5"], "argument --thresholds: 1.5 is outside (0, 1]"),
        (["--thresholds", "0.5,-0.2"], "argument --thresholds: -0.2 is outside (0, 1]"),
        (["--thresholds", "50,80"], "argument --thresholds: 50 is outside (0, 1]"),
        (["--thresholds", "half"], "argument --thresholds: 'half' is not a number"),
        (["--thresholds", "0.5,0.5"], "argument --thresholds: a threshold is given twice"),
        (["--fdr", "0"], "argument --fdr: 0 is outside (0, 1)"),
        (["--fdr", "1"], "argument --fdr: 1 is outside (0, 1)"),
        (["--fdr", "x"], "argument --fdr: 'x' is not a number"),
        (["--baseline", "dagger"], "argument --baseline: invalid choice: 'dagger'"),
    ],
)
def test_bad_options_are_rejected(
    args: list[str],
    message: str,
    export: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    out = tmp_path / "out"
    code, _, stderr = analyze(capsys, "--data", export, "--out", out, *args)
    assert code == 2
    assert "bam-study analyze: error: " + message in stderr
    assert not out.exists()


def test_a_threshold_of_one_is_allowed(
    export: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert analyze(capsys, "--data", export, "--out", tmp_path / "o", "--thresholds", "1")[0] == 0


def test_a_baseline_absent_from_the_data(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    sessions = [s for s in small_study() if s[3] != "cloning"]
    export = write_export(tmp_path / "export", sessions)
    out = tmp_path / "out"
    code, _, stderr = analyze(capsys, "--data", export, "--out", out, "--baseline", "cloning")
    assert code == 2
    assert (
        "bam-study analyze: error: --baseline: no learning sessions of 'cloning' in the data "
        "(learners present: bam, model-based)"
    ) in stderr
    assert not out.exists()


@pytest.mark.parametrize(
    ("participants", "message"),
    [
        (None, "--exclude-excluded needs participants.csv, which is not in"),
        (
            "participant_id,state\np1,excluded\n",
            "participants.csv: --exclude-excluded needs the columns 'participant_id' and "
            "'excluded' (or 'status')",
        ),
    ],
)
def test_exclude_excluded_needs_participant_statuses(
    participants: str | None,
    message: str,
    export: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    if participants is None:
        (export / "participants.csv").unlink()
    else:
        (export / "participants.csv").write_text(participants, encoding="utf-8")
    out = tmp_path / "out"
    code, _, stderr = analyze(capsys, "--data", export, "--out", out, "--exclude-excluded")
    assert code == 2
    assert message in stderr
    assert not out.exists()


def test_out_must_be_a_folder(
    export: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out.txt"
    out.write_text("a file", encoding="utf-8")
    code, _, stderr = analyze(capsys, "--data", export, "--out", out)
    assert code == 2
    assert "--out: " in stderr and "is not a folder" in stderr
    assert out.read_text(encoding="utf-8") == "a file"


def test_the_console_command_reports_bad_input_on_stderr(export: Path, tmp_path: Path) -> None:
    set_cell("evaluations.csv", 2, "episodes", "-3")(export)
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "server.commands.main",
            "analyze",
            "--data",
            str(export),
            "--out",
            str(tmp_path / "o"),
        ],
        capture_output=True,
        text=True,
        check=False,
    )
    assert result.returncode == 2
    assert result.stdout == ""
    assert result.stderr == (
        "bam-study analyze: error: evaluations.csv, row 2 (line 3), column 'episodes': "
        "-3 is negative\n"
    )


def test_the_subcommand_is_registered_without_loading_the_analysis_libraries() -> None:
    # What `bam-study --help` does for this subcommand: import server.commands.analyze and configure.
    code = (
        "import argparse, sys; from server.commands.main import SUBCOMMANDS; import server.commands.analyze as c; "
        "assert SUBCOMMANDS['analyze'][0] == 'server.commands.analyze'; c.configure(argparse.ArgumentParser()); "
        "print(sorted(m for m in ('pandas', 'scipy', 'statsmodels', 'matplotlib') "
        "if m in sys.modules))"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    )
    assert result.stdout.strip() == "[]"


def test_the_report_says_how_many_empty_episodes_it_left_out(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    study = small_study()
    first = study[0]
    # Two tries from the goal in the first session (updates 2 and 3 of its curve).
    empty = [
        {
            "session_id": first[0],
            "kind": "agent",
            "start_state": 5,
            "end_state": 5,
            "end_reason": "goal",
            "actions": 1,
            "update_index": update,
        }
        for update in (2, 3)
    ]
    export = write_export(tmp_path / "export", study, episodes=empty)
    code, out, err = analyze(capsys, "--data", export, "--out", tmp_path / "out")
    assert code == 0, err
    table = (tmp_path / "out" / "table1.md").read_text()
    assert "- 2 empty episodes in 1 learning session not counted" in table
    assert "2 empty episodes in 1 learning session not counted" in out
    readme = (tmp_path / "out" / "README.md").read_text()
    assert "empty episodes are not counted" in readme
    summary = {r["session_id"]: r for r in read_rows(tmp_path / "out" / "sessions_summary.csv")}
    # 50% at update 1 (before the empty episodes), 80% at update 2: 3 episodes as exported,
    # of which the one ended by update 2 was empty.
    assert (summary[first[0]]["episodes_50"], summary[first[0]]["episodes_80"]) == ("2", "2")
    assert summary[first[0]]["actions_80"] == "38"
