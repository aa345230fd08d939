"""The deployment's servers as the dashboard lists them: each running server with its
heartbeat, machine and load, the one that answered marked, and a stopped one shown stopped."""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor

from fastapi.testclient import TestClient

from server.app.main import create_app
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.study_file import StudyConfig
from server.app.updates.servers import this_machine
from server.cores import available_cores
from tests.support.server import ADMIN_TOKEN

ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}


def test_the_dashboard_lists_each_server(
    db: Database, settings: Settings, study: StudyConfig, executor: ProcessPoolExecutor
) -> None:
    first = TestClient(create_app(settings, study, db=db, executor=executor))
    second = TestClient(create_app(settings, study, db=db, executor=executor))
    with first:
        with second:
            listed = first.get("/api/admin/servers", headers=ADMIN)
            assert listed.status_code == 200, listed.text
            rows = listed.json()
            assert len(rows) == 2 and all(row["live"] for row in rows)
            assert [row["this_server"] for row in rows].count(True) == 1
            assert all(row["update_slots"] >= 1 and row["stopped_at"] is None for row in rows)
            # Both in this process: one machine, whose cores their update processes share.
            assert [row["machine"] for row in rows] == [this_machine()] * 2
            assert all(row["cores"] == available_cores() for row in rows)
            assert second.get("/api/admin/servers", headers=ADMIN).json()[0]["this_server"]
        # The second server stopped: it is listed as stopped, no longer live.
        rows = first.get("/api/admin/servers", headers=ADMIN).json()
        stopped = [row for row in rows if not row["this_server"]]
        assert len(stopped) == 1 and not stopped[0]["live"] and stopped[0]["stopped_at"]
        assert first.get("/api/admin/servers").status_code == 401
        page = first.get("/dashboard", headers=ADMIN)
        assert page.status_code == 200 and 'id="servers"' in page.text
