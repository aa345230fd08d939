"""`bam-study analyze --database-url` on a study the server ran (SQLite and PostgreSQL): the
same results as from the export; participants the experimenter excluded through the admin API
are dropped with --exclude-excluded, from the database and from the export alike; a database
that is not a study's is refused clearly."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
from fastapi.testclient import TestClient

from server.app.storage.db import Database
from server.commands.main import main
from tests.app.export.test_export import study_run  # noqa: F401  (the fixture)
from tests.support.server import ADMIN_TOKEN

RESULTS = ("table1.md", "table1.tex", "sessions_summary.csv", "comparisons.csv", "appendix_raw.md")


def analyze(capsys: pytest.CaptureFixture[str], *args: str | Path) -> tuple[int, str, str]:
    try:
        code = main(["analyze", *(str(a) for a in args)])
    except SystemExit as exit:  # argparse refused the arguments
        code = int(exit.code or 0)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


@pytest.mark.slow
def test_the_database_and_its_export_give_the_same_results(
    study_run: list,  # noqa: F811
    client: TestClient,
    db: Database,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    url = db.engine.url.render_as_string(hide_password=False)
    assert main(["export", "--database-url", url, "--out", str(tmp_path / "export")]) == 0
    capsys.readouterr()
    code, from_export, err = analyze(capsys, "--data", tmp_path / "export", "--out", tmp_path / "a")
    assert code == 0, err
    code, from_database, err = analyze(capsys, "--database-url", url, "--out", tmp_path / "b")
    assert code == 0, err
    for name in RESULTS:
        assert (tmp_path / "a" / name).read_text() == (tmp_path / "b" / name).read_text(), name
    # The same printout too (but for the folder it names).
    assert from_export.split("Results written")[0] == from_database.split("Results written")[0]
    summary = pd.read_csv(tmp_path / "b" / "sessions_summary.csv")
    assert len(summary) == 12  # two participants, six agents each
    assert summary["participant_id"].nunique() == 2
    assert "12 learning sessions of 2 participants in 4 environments" in from_database

    # The experimenter excludes the first participant through the admin API.
    first = int(summary["participant_id"].min())
    response = client.post(
        f"/api/admin/participants/{first}/exclusion",
        json={"reason": "did not follow the instructions"},
        headers={"Authorization": f"Bearer {ADMIN_TOKEN}"},
    )
    assert response.status_code == 200, response.text
    assert main(["export", "--database-url", url, "--out", str(tmp_path / "export2")]) == 0
    capsys.readouterr()
    for source in (["--database-url", url], ["--data", str(tmp_path / "export2")]):
        out = tmp_path / f"excluded-{source[0][2:]}"
        code, stdout, err = analyze(capsys, *source, "--out", out, "--exclude-excluded")
        assert code == 0, err
        assert "excluded 6 learning sessions of 1 participant marked excluded" in stdout
        kept = pd.read_csv(out / "sessions_summary.csv")
        assert len(kept) == 6 and first not in set(kept["participant_id"])
        # Without the flag they stay in, with a remark.
        code, stdout, _ = analyze(capsys, *source, "--out", tmp_path / f"all-{source[0][2:]}")
        assert code == 0
        assert "6 learning sessions of participants marked excluded" in stdout


def test_a_database_that_is_not_a_study_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import sqlite3

    other = tmp_path / "other.sqlite"
    with sqlite3.connect(other) as connection:
        connection.execute("CREATE TABLE notes (text TEXT)")
    before = other.read_bytes()
    out = tmp_path / "out"
    code, _, err = analyze(capsys, "--database-url", f"sqlite:///{other}", "--out", out)
    assert code == 2
    assert "the schema is at revision none" in err and "not a study database" in err
    assert other.read_bytes() == before
    assert not out.exists()


@pytest.mark.parametrize(
    ("url", "message"),
    [
        ("not a url", "is not a database URL"),
        ("sqlite://", "a SQLite URL needs the database file"),
        ("sqlite:///{tmp}/missing.sqlite", "no database file"),
        ("postgresql+psycopg://postgres@127.0.0.1:1/test", "cannot read the database"),
    ],
)
def test_bad_database_urls_are_refused(
    url: str, message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    code, _, err = analyze(capsys, "--database-url", url.format(tmp=tmp_path), "--out", out)
    assert code == 2
    assert message in err
    assert not out.exists()
    assert not (tmp_path / "missing.sqlite").exists()  # nothing created on the way


def test_data_and_database_url_are_exclusive(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, _, err = analyze(
        capsys, "--data", tmp_path, "--database-url", "sqlite:///x", "--out", tmp_path / "o"
    )
    assert code == 2
    assert "not allowed with argument" in err
