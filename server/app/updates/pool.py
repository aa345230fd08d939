"""The local pool of update processes, and the failures an update's processes report to the
server."""

from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    pass


from server.app.updates.worker import worker_init


class WorkerDied(RuntimeError):
    """The processes running an update died ``deaths`` times."""

    def __init__(self, deaths: int = 1) -> None:
        super().__init__("the update process died")
        self.deaths = deaths


class UpdatesUnavailable(ConnectionError):
    """The updates' cluster cannot be reached: the update stays pending and is tried again."""


def new_executor(workers: int, niceness: int) -> ProcessPoolExecutor:
    # Spawned, not forked: the server process has threads.
    return ProcessPoolExecutor(
        max_workers=workers,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=worker_init,
        initargs=(niceness, os.getpid()),
    )
