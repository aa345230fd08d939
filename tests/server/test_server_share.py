"""The server's own work per update, timed at start on a scratch copy of the study."""

from __future__ import annotations

import math
import multiprocessing
import threading
import time

import pytest
from sqlalchemy import func, select

from server.app.config import StudyConfig
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.storage.models import LearnerUpdate, Participant
from server.commands.server_share import Stopped, measure_server_share


def count(db: Database, table: type[Participant] | type[LearnerUpdate]) -> int:
    with db.read() as s:
        return int(s.scalar(select(func.count()).select_from(table)) or 0)


def test_the_servers_share_is_timed_on_a_scratch_copy_and_not_in_the_study(
    db: Database, settings: Settings, study: StudyConfig
) -> None:
    share = measure_server_share(settings, study, participants=2, seconds=3.0, warm_seconds=1.0)
    # CPU seconds of the scratch server's process per update queued: some, and less than
    # the whole of the 3 s the two participants taught for (the updates ran elsewhere).
    assert math.isfinite(share) and 0 < share < 3.0
    # The study's own database has no participant and no update of the scratch copy's.
    assert count(db, Participant) == 0 and count(db, LearnerUpdate) == 0


def test_a_stopped_timing_ends_its_scratch_study_and_says_so(
    settings: Settings, study: StudyConfig
) -> None:
    """A server stopped while it times its own work does not wait for the timing's end: the
    scratch study stops at once and no process is left behind."""
    stop = threading.Event()
    stop.set()
    before = {child.pid for child in multiprocessing.active_children()}
    started = time.monotonic()
    with pytest.raises(Stopped):
        measure_server_share(settings, study, stop, seconds=600.0, warm_seconds=600.0)
    # Well before the 20 minutes the timing would take (a generous bound: the scratch
    # process starts, and may load the learners, before it sees the stop).
    assert time.monotonic() - started < 300
    assert {child.pid for child in multiprocessing.active_children()} <= before
