"""The server's log holds no participant's platform id: uvicorn's access log (``serve
--access-log``) and httpx's line per request write each id as the export's pseudonym, so no
erasure or scrub has to reach the log files."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from server.app.rights.log_ids import LOGGERS, PseudonymousIds, keep_ids_out_of_logs
from server.app.rights.pseudonyms import database_secret, pseudonym
from server.app.storage.db import Database
from tests.support.databases import migrated_sqlite
from tests.support.server import gated_app, live, make_settings, study_config

PID = "5f4e3d2c1b0a99887766aabb"
SESSION = "6a5b4c3d2e1f00112233ccdd"
STUDY = "7c6d5e4f3a2b1c0d9e8f7a6b"
WORKER, ASSIGNMENT = "A1B2C3D4E5F6G7", "3ASSIGNMENTIDXYZ1234567890AB"


@pytest.fixture
def forgotten() -> Iterator[None]:
    yield
    for name in LOGGERS:
        logger = logging.getLogger(name)
        for installed in [f for f in logger.filters if isinstance(f, PseudonymousIds)]:
            logger.removeFilter(installed)


def test_logged_requests_carry_pseudonyms_not_platform_ids(
    tmp_path: Path,
    capfd: pytest.CaptureFixture[str],
    caplog: pytest.LogCaptureFixture,
    forgotten: None,
) -> None:
    db = Database.from_url(migrated_sqlite(tmp_path / "study.db"))
    try:
        secret = database_secret(db)
        app, _ = gated_app(db, make_settings(str(db.engine.url)), study_config())
        caplog.set_level(logging.INFO, logger="httpx")
        with live(app, log_level="info", access_log=True) as url:
            keep_ids_out_of_logs(secret)
            prolific = f"{url}/study?PROLIFIC_PID={PID}&STUDY_ID={STUDY}&SESSION_ID={SESSION}"
            mturk = f"{url}/study?assignmentId={ASSIGNMENT}&hitId=H1&workerId={WORKER}"
            with httpx.Client() as client:
                for address in (prolific, mturk, f"{url}/prolific/api/v1/submissions/{SESSION}/"):
                    client.get(address)
    finally:
        db.dispose()
    out, err = capfd.readouterr()
    written = out + err + caplog.text
    assert "HTTP Request: GET" in caplog.text and '"GET /study?' in written
    for raw in (PID, SESSION, WORKER, ASSIGNMENT):
        assert raw not in written
    for value, prefix in ((PID, "w"), (SESSION, "a"), (WORKER, "w"), (ASSIGNMENT, "a")):
        assert str(pseudonym(secret, value, prefix)) in written
    assert f"STUDY_ID={STUDY}" in written and "hitId=H1" in written  # not a person's
    assert f"/submissions/{pseudonym(secret, SESSION, 'a')}/" in written


def test_an_access_log_record_keeps_its_arguments_for_uvicorn_s_formatter() -> None:
    """uvicorn's access formatter unpacks the record's five arguments, the status an int."""
    ids = PseudonymousIds("k" * 64)
    record = logging.LogRecord(
        "uvicorn.access",
        logging.INFO,
        __file__,
        1,
        '%s - "%s %s HTTP/%s" %d',
        ("127.0.0.1:5000", "GET", f"/study?SESSION_ID={SESSION}&x=1", "1.1", 200),
        None,
    )
    assert ids.filter(record)
    assert record.args is not None and len(record.args) == 5
    path, status = record.args[2], record.args[4]
    assert path == f"/study?SESSION_ID={pseudonym('k' * 64, SESSION, 'a')}&x=1" and status == 200
