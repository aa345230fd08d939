"""A study database opened to read (the export, the analysis) is never written, not even by
the log's checkpoint that a study server's stop runs."""

from __future__ import annotations

from pathlib import Path

import pytest

from server.app.storage import db as db_module
from server.app.storage.db import Database, open_study_database


def test_disposing_a_database_opened_to_read_checkpoints_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    truncated: list[object] = []
    monkeypatch.setattr(db_module, "_truncate_wal", lambda engine, **_: truncated.append(engine))
    url = f"sqlite:///{tmp_path / 'study.sqlite'}"
    written = Database.from_url(url)
    with written.engine.begin() as connection:
        connection.exec_driver_sql("CREATE TABLE t (x INTEGER)")
    written.dispose()
    assert truncated == [written.engine]  # the server's stop truncates the log it wrote

    read = open_study_database(url)
    assert read.read_only
    read.dispose()
    assert truncated == [written.engine]
