"""The capacity a deployment of several servers states: each machine's cores counted once,
however many servers share it (each server alone counts all of the machine's cores), the
machines' capacities added, and a Dask cluster that several servers use counted once."""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import update

from server.app.main import create_app
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import StudyServer, utcnow
from server.app.study_file import StudyConfig
from server.app.updates.capacity import (
    ServerSlots,
    deployment_participants,
    participants_at_once,
)
from server.app.updates.servers import slots_machine, this_machine
from tests.support.server import ADMIN_TOKEN, wait_until

ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}


def local(machine: str, slots: int = 1, cores: int = 2, server: float | None = 0.05) -> ServerSlots:
    return ServerSlots(machine, slots, cores, update_seconds=0.25, server_seconds=server)


def test_servers_on_one_machine_share_its_cores_and_machines_add_up() -> None:
    # Each of three servers with one update process on a 2-core machine, alone: 75% of
    # 1 slot x 10 s / 0.25 s = 30, so 90 summed. Together they have the machine's 2 cores,
    # which also do the servers' own 0.05 s a update: 75% x 2 x 10 s / 0.30 s = 50.
    alone = participants_at_once(0.25, 1, 10.0, server_seconds=0.05, cores=2)
    assert alone == 30
    one_machine = [local("A"), local("A"), local("A")]
    assert deployment_participants(one_machine, 10.0) == (50, 2)
    # Two such machines: twice the capacity and the slots.
    assert deployment_participants([*one_machine, local("B"), local("B")], 10.0) == (100, 4)
    # A server alone on its machine states its own capacity.
    assert deployment_participants([local("A")], 10.0) == (alone, 1)
    # Costs are averaged over a machine's slots: 0.25 s and 0.75 s, one slot each, on 2 cores
    # with no server work counted: 75% x 2 slots x 10 s / 0.5 s = 30.
    slow = ServerSlots("A", 1, 2, update_seconds=0.75, server_seconds=None)
    assert deployment_participants([local("A", server=None), slow], 10.0) == (30, 2)


def test_servers_of_one_dask_cluster_count_its_workers_once() -> None:
    # Two servers send their updates to one cluster of 4 worker threads: 4 slots, not 8, and
    # no cores bound (the workers are not the servers' machines').
    cluster = [ServerSlots("dask tcp://10.0.0.5:8786", 4, None, 0.25, None)] * 2
    assert deployment_participants(cluster, 10.0) == (participants_at_once(0.25, 4, 10.0), 4)
    assert slots_machine("tcp://10.0.0.5:8786") == "dask tcp://10.0.0.5:8786"
    # A scheduler on a loopback address is this machine's own: another machine's is another.
    assert slots_machine("tcp://127.0.0.1:8786") == f"dask tcp://127.0.0.1:8786 on {this_machine()}"
    assert slots_machine(None) == this_machine()


@pytest.mark.parametrize("backend", ["postgresql"])
def test_a_deployment_states_each_machines_cores_once(
    db: Database,
    settings: Settings,
    study: StudyConfig,
    executor: ProcessPoolExecutor,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # A 2-core machine whatever the test's: each server has two update processes on it.
    for module in ("server.app.updates.runners", "server.app.updates.manager"):
        monkeypatch.setattr(f"{module}.available_cores", lambda: 2)
    quick = settings.model_copy(update={"update_workers": 2, "update_lease_seconds": 3.0})
    apps = [create_app(quick, study, db=db, executor=executor) for _ in range(2)]
    with TestClient(apps[0]) as first, TestClient(apps[1]):
        managers = [app.state.server.updates for app in apps]
        for manager in managers:
            manager.reference_seconds = 0.25  # as if timed at start
        alone = participants_at_once(0.25, 2, 10.0)
        assert alone == 60 and all(m.capacity().participants == alone for m in managers)

        def queue() -> dict[str, object]:
            answer = first.get("/api/admin/queue", headers=ADMIN)
            assert answer.status_code == 200, answer.text
            return dict(answer.json())

        # Both servers' heartbeats name the same machine: the deployment has its 2 cores, once.
        wait_until(
            lambda: "other servers" in str(queue()["measured_on"]),
            "the first server read the second's heartbeat",
        )
        both = queue()
        assert (both["capacity"], both["slots"]) == (alone, 2), both

        def servers() -> list[dict[str, object]]:
            return list(first.get("/api/admin/servers", headers=ADMIN).json())

        wait_until(
            lambda: all(row["update_seconds"] == 0.25 for row in servers()),
            "each server's heartbeat said the cost its capacity came from",
        )
        rows = servers()
        assert [row["machine"] for row in rows] == [this_machine()] * 2
        assert all(row["cores"] == 2 for row in rows)

        # A server on another machine, beating: its cores add to the deployment's.
        with db.write() as s:
            s.add(
                StudyServer(
                    name="elsewhere-1-abc123", host="elsewhere", pid=1, machine="another boot",
                    cores=2, update_slots=2, updates_running=0, updates_completed=0,
                    updates_failed=0, participants_at_once=alone, update_seconds=0.25,
                )
            )  # fmt: skip

        def beat_elsewhere_and_read() -> dict[str, object]:
            with db.write() as s:
                s.execute(
                    update(StudyServer)
                    .where(StudyServer.name == "elsewhere-1-abc123")
                    .values(heartbeat_at=utcnow())
                )
            return queue()

        wait_until(
            lambda: beat_elsewhere_and_read()["capacity"] == 2 * alone,
            "the deployment counted the other machine's cores",
            timeout=30,
        )
        assert beat_elsewhere_and_read()["slots"] == 4
