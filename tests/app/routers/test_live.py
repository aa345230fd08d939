"""The live views: the funnel's counts are the database's at the same moment (as JSON and as
server-sent events), every watcher of a view shares one snapshot per interval, the mirror reads
a participant's session without a trace and without an identifier and follows them from agent
to agent, and the live curves are the analysis's computation."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient
from pydantic import ValidationError
from sqlalchemy import func, select, text

from analysis.options import DEFAULT_THRESHOLDS
from server.app.live import curves, funnel
from server.app.live.broadcast import Broadcast
from server.app.live.mirror import mirror_view
from server.app.live.views import LiveViews
from server.app.main import create_app
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import Event, Participant, utcnow
from server.app.study_file import StudyConfig
from tests.support.server import (
    ADMIN_TOKEN,
    demonstrate_each_task,
    live,
    new_participant,
    run_apart,
    study_config,
    teaching_participant,
    wait_for_updates,
)

ADMIN = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
LIVE = "/api/admin/live"
DEVICE = {"arrow_key": False, "width": 1280, "height": 800, "missing": []}


@pytest.fixture
def study() -> StudyConfig:
    return study_config(device_check={"enabled": True})


def statuses_in_database(db: Database) -> dict[str, int]:
    with db.read() as s:
        rows = s.execute(
            select(Participant.status, func.count()).group_by(Participant.status)
        ).all()
    return {status: count for status, count in rows}


def nonzero(counts: dict[str, int]) -> dict[str, int]:
    return {key: value for key, value in counts.items() if value}


def several_stages(client: httpx.Client | TestClient) -> None:
    """Participants at consent, turned away, declined, in the tutorial and at agent 1."""
    new_participant(client, "W1", "A1")  # at consent
    client.cookies.clear()
    away = new_participant(client, "W2", "A2")
    away.act("/api/participant/device-check", **DEVICE)
    client.cookies.clear()
    declined = new_participant(client, "W3", "A3")
    declined.act("/api/participant/consent", agree=False)
    client.cookies.clear()
    teaching_participant(client, "W4", "A4")  # the tutorial
    client.cookies.clear()
    teacher, tutorial = teaching_participant(client, "W5", "A5")
    teacher.act(f"/api/sessions/{tutorial}/finish")  # on to agent 1
    client.cookies.clear()


def test_the_funnel_counts_each_stage_as_the_database_does(
    client: TestClient, db: Database
) -> None:
    several_stages(client)
    snapshot = client.get(f"{LIVE}/funnel", headers=ADMIN).json()
    assert nonzero(snapshot["statuses"]) == statuses_in_database(db)
    assert snapshot["participants_total"] == sum(statuses_in_database(db).values()) == 5
    assert nonzero(snapshot["stages"]) == {
        "consent": 1,
        "incompatible": 1,
        "declined": 1,
        "tutorial": 1,
        "agent": 1,
    }
    assert snapshot["agents"] == {"1": 1}
    listed = {row["stage"]: row for row in snapshot["participants"]}
    assert set(listed) == {"consent", "tutorial", "agent"}  # in progress only
    assert listed["agent"]["agent"] == 1 and listed["agent"]["agents"] == 6
    assert all(row["seconds_there"] >= 0 and not row["idle"] for row in listed.values())
    # Idle too long: no request for longer than IDLE_MINUTES.
    with db.transaction() as c:
        c.execute(
            text("UPDATE participants SET last_seen_at = :at WHERE platform_participant_id = 'W4'"),
            {"at": "2000-01-01 00:00:00"},
        )
    again = client.get(f"{LIVE}/funnel", headers=ADMIN).json()
    assert again["idle"] == 1
    assert [row["stage"] for row in again["participants"] if row["idle"]] == ["tutorial"]


def test_the_live_views_are_behind_the_admin_token(client: TestClient) -> None:
    for path in ("/funnel", "/funnel/stream", "/curves", "/participants/1/mirror"):
        assert client.get(f"{LIVE}{path}").status_code == 401
    assert client.get(f"{LIVE}/participants/99/mirror", headers=ADMIN).status_code == 404
    assert client.get(f"{LIVE}/participants/99/mirror/stream", headers=ADMIN).status_code == 404
    assert client.get("/dashboard/live", follow_redirects=False).status_code == 303


def events_of(response: httpx.Response) -> Iterator[tuple[str, str, dict[str, Any]]]:
    """(event, id, data) of each server-sent event of the stream."""
    fields: dict[str, str] = {}
    for line in response.iter_lines():
        if line == "":
            if "data" in fields:
                yield (
                    fields.get("event", "message"),
                    fields.get("id", ""),
                    json.loads(fields["data"]),
                )
            fields = {}
        elif not line.startswith(":") and ":" in line:
            name, _, value = line.partition(":")
            fields[name] = value.removeprefix(" ")


@pytest.fixture
def served(
    db: Database, settings: Settings, study: StudyConfig, executor: ProcessPoolExecutor
) -> Iterator[tuple[str, Any]]:
    app = create_app(settings, study, db=db, executor=executor)
    with live(app) as base:
        yield base, app


def test_the_streamed_funnel_equals_the_database_at_each_moment(
    served: tuple[str, Any], db: Database
) -> None:
    base, app = served
    with httpx.Client(base_url=base) as browser:
        several_stages(browser)
    with (
        httpx.Client(base_url=base, headers=ADMIN, timeout=60) as watcher,
        watcher.stream("GET", f"{LIVE}/funnel/stream") as response,
    ):
        assert response.status_code == 200
        assert response.headers["content-type"].startswith("text/event-stream")
        stream = events_of(response)
        event, _, first = next(stream)
        assert event == "funnel"
        assert nonzero(first["statuses"]) == statuses_in_database(db)
        # Another arrives, and one teaching leaves (returned): the next snapshots follow.
        with httpx.Client(base_url=base) as browser:
            new_participant(browser, "W6", "A6")
        with db.transaction() as c:
            c.execute(
                text(
                    "UPDATE participants SET status = 'returned' WHERE platform_participant_id = 'W4'"
                )
            )
        for _, _, snapshot in stream:
            if snapshot["stages"]["returned"] == 1 and snapshot["participants_total"] == 6:
                break
        assert nonzero(snapshot["statuses"]) == statuses_in_database(db)
        assert snapshot["stages"]["consent"] == 2 and snapshot["stages"]["tutorial"] == 0
    assert app.state.live.funnel.watchers in (0, 1)  # the stream closed (or is closing)


def test_the_live_views_intervals_are_the_deployment_s_settings(
    db: Database, settings: Settings, study: StudyConfig, executor: ProcessPoolExecutor
) -> None:
    chosen = settings.model_copy(
        update={"live_funnel_seconds": 5.0, "live_curves_seconds": 30.0, "live_mirror_seconds": 1.5}
    )
    views = create_app(chosen, study, db=db, executor=executor).state.live
    assert (views.funnel.interval, views.curves.interval) == (5.0, 30.0)
    assert views.mirror(1).interval == 1.5
    for name, value in (("live_mirror_seconds", 0), ("live_funnel_seconds", -1)):
        with pytest.raises(ValidationError, match=name):
            Settings(**{name: value})


def test_every_watcher_of_a_view_shares_one_snapshot_per_interval() -> None:
    async def scenario() -> tuple[int, list[list[tuple[str, int]]]]:
        calls = 0

        async def compute() -> dict[str, Any]:
            nonlocal calls
            calls += 1
            return {"call": calls}

        broadcast = Broadcast(compute, 0.01)
        seen: list[list[tuple[str, int]]] = []

        async def watcher() -> None:
            got: list[tuple[str, int]] = []
            async for message in broadcast.watch("x"):
                if message.startswith("event"):
                    lines = dict(line.split(": ", 1) for line in message.strip().split("\n"))
                    got.append((lines["id"], json.loads(lines["data"])["call"]))
                if len(got) == 3:
                    break
            seen.append(got)

        await asyncio.gather(*(watcher() for _ in range(3)))
        made = calls
        await broadcast.stop()
        return made, seen

    made, seen = run_apart(scenario)
    # Three watchers, one computation per snapshot: each sees the same ids and the same data.
    assert [version for version, _ in seen[0]] == [str(n) for n in range(1, 4)]
    assert seen[0] == seen[1] == seen[2]
    assert made <= 4  # at most one computed ahead of the last read, never one per watcher


def test_the_mirror_leaves_no_trace_shows_no_identifier_and_follows_the_participant(
    client: TestClient, db: Database
) -> None:
    teacher, tutorial = teaching_participant(client, "WMIRROR1", "AMIRROR1")
    teacher.act(f"/api/sessions/{tutorial}/open")
    teacher.act(f"/api/sessions/{tutorial}/move", action="LEFT")

    def trace() -> tuple[Any, ...]:
        with db.read() as s:
            p = s.scalars(select(Participant)).one()
            events = s.scalar(select(func.count()).select_from(Event))
            return p.id, p.next_seq, p.last_seen_at, p.status, events

    before = trace()
    participant_id = before[0]
    view = client.get(f"{LIVE}/participants/{participant_id}/mirror", headers=ADMIN).json()
    assert trace() == before
    assert view["status"] == "tutorial"
    session = view["session"]
    assert session["kind"] == "tutorial" and session["agent"] is None
    assert session["teaching"]["agent"] is not None
    assert [e["kind"] for e in session["recent"]][:2] == ["move", "open"]
    text_of_view = json.dumps(view)
    for identifier in ("WMIRROR1", "AMIRROR1", teacher.token, '"participant_id"', "session_id"):
        assert identifier not in text_of_view
    # On to the first study agent: the mirror follows.
    teacher.act(f"/api/sessions/{tutorial}/finish")
    following = client.get(f"{LIVE}/participants/{participant_id}/mirror", headers=ADMIN).json()
    assert following["status"] == "teaching"
    assert following["session"]["kind"] == "study" and following["session"]["agent"] == 1
    assert following["session"]["of"] == 6
    current = teacher.get("/api/participant")["current_session_id"]
    teacher.act(f"/api/sessions/{current}/open")
    demonstrate_each_task(teacher, current)
    teacher.act(f"/api/sessions/{current}/finish")
    second = client.get(f"{LIVE}/participants/{participant_id}/mirror", headers=ADMIN).json()
    assert second["session"]["agent"] == 2


def test_the_live_curves_are_the_analysis_s_computation() -> None:
    assert curves.THRESHOLDS == DEFAULT_THRESHOLDS
    from analysis import plots

    assert plots.step_values is curves.step_values
    assert plots.mean_and_standard_error is curves.mean_and_standard_error
    grid = np.array([0.0, 1.0, 2.0, 3.0])
    first = curves.step_values(np.array([1.0, 3.0]), np.array([0.2, 0.6]), grid)
    second = curves.step_values(np.array([0.0, 2.0]), np.array([0.4, 1.0]), grid)
    mean, se, n = curves.mean_and_standard_error(np.vstack([first, second]))
    assert np.allclose(mean, [0.4, 0.3, 0.6, 0.8])
    assert list(n) == [1, 2, 2, 2]
    assert np.isnan(se[0]) and np.isclose(se[1], np.std([0.2, 0.4], ddof=1) / np.sqrt(2))


def test_the_live_views_read_in_a_process_of_their_own_that_is_replaced_when_it_dies(
    client: TestClient, db: Database
) -> None:
    """BAM_LIVE_READER=process (the default): the funnel, the curves and the mirror are read in
    another process, and they are what the server's own reads give; a reader killed is
    replaced at the next read, and the server's stop takes the reader with it."""
    several_stages(client)
    teacher, tutorial = teaching_participant(client, "WREAD", "AREAD")
    teacher.act(f"/api/sessions/{tutorial}/open")
    teacher.act(f"/api/sessions/{tutorial}/move", action="LEFT")
    wait_for_updates(db)  # the funnel's queue is the same at both reads
    with db.read() as s:
        participant_id = s.scalar(
            select(Participant.id).where(Participant.platform_participant_id == "WREAD")
        )
    assert participant_id is not None
    state = client.app.state.server  # type: ignore[attr-defined]
    assert state.settings.live_reader == "process"

    def without_clock(snapshot: dict[str, Any]) -> dict[str, Any]:
        return {k: v for k, v in snapshot.items() if k not in ("participants", "at", "queue")}

    async def scenario() -> tuple[Any, ...]:
        views = LiveViews(state)
        assert views.reader is not None
        funnel_read = await views._funnel()
        first = views.reader.pid
        curves_read = await views._curves()
        mirror = views.mirror(participant_id)
        await mirror._tick()
        mirrored = json.loads(mirror.latest or "null")
        assert first is not None
        os.kill(first, signal.SIGKILL)
        teacher.act(f"/api/sessions/{tutorial}/move", action="RIGHT")
        await mirror._tick()  # the reader was killed: another reads
        second = views.reader.pid
        moved = json.loads(mirror.latest or "null")
        await views.stop()
        return funnel_read, curves_read, mirrored, moved, first, second

    funnel_read, curves_read, mirrored, moved, first, second = run_apart(scenario)
    assert first is not None and second is not None and len({first, second, os.getpid()}) == 3
    with db.connect() as c:
        assert without_clock(funnel_read) == without_clock(funnel.funnel(c, utcnow()))
        assert curves_read == curves.live_curves(c)
        view = mirror_view(c, state.study, participant_id)
    assert moved == json.loads(json.dumps(view))
    assert [e["action"] for e in moved["session"]["recent"][:2]] == ["RIGHT", "LEFT"]
    assert [e["action"] for e in mirrored["session"]["recent"][:1]] == ["LEFT"]
    with pytest.raises(ProcessLookupError):  # the reader stopped with the views
        for _ in range(100):
            os.kill(second, 0)
            time.sleep(0.05)
