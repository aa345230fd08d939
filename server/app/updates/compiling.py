"""One process at a time through the warm-up on a machine, so the learners' kernels are compiled
once per machine, not once per process.

Where numba's on-disk cache lacks the kernels (a new checkout, a new container, another CPU),
every process that warms up compiles them itself: a server's two update processes compiled the
same kernels side by side, two minutes of each core. Under this lock the first process compiles
and writes the cache; the others wait, then load what it wrote (about a second each).
"""

from __future__ import annotations

import fcntl
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import server.learners

LOCK_NAME = "bam-warm-up.lock"


def lock_path() -> Path:
    """Beside the kernels' cache: numba's own folder for server/learners (``__pycache__``, or
    under NUMBA_CACHE_DIR), so processes that share a cache share the lock."""
    cache_dir = os.environ.get("NUMBA_CACHE_DIR")
    if cache_dir:
        return Path(cache_dir) / LOCK_NAME
    return Path(server.learners.__file__).parent / "__pycache__" / LOCK_NAME


@contextmanager
def one_warm_up_at_a_time() -> Iterator[None]:
    """Held while this process warms up; waits while another process on the machine does.
    Where the lock's folder cannot be written (a read-only install), nothing is held: each
    process compiles for itself, as without the lock."""
    path = lock_path()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle = open(path, "a")
    except OSError:
        yield
        return
    try:
        fcntl.flock(handle, fcntl.LOCK_EX)
        yield
    finally:
        handle.close()  # releases the lock
