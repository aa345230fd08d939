"""Whether numba's on-disk cache holds the learners' kernels, so that a command about to run
the learners in its own process says so before minutes of compiling, not after.

numba keeps a kernel compiled with ``cache=True`` as an index file (``.nbi``) and data files
beside its source (``__pycache__``) or under ``NUMBA_CACHE_DIR``. A missing index, or one older
than ``_kernels.py``, means the next call compiles (about a minute of a core). The check
reads one kernel's index, a guess that errs only towards saying nothing: an index made for
another CPU is rebuilt without a word.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TextIO

from server.learners import _kernels

# What a compile costs, as the commands say it (docs/benchmarks.md has the measurement).
COMPILE_TIME = "about a minute of a core"


def kernels_cached() -> bool:
    """True when numba's cache has an index for the learners' planner kernel that is at least
    as new as their source (True also when numba's cache cannot be located)."""
    cache = getattr(_kernels.soft_forward_tasks, "_cache", None)  # numba's, not public
    folder = getattr(cache, "_cache_path", None)
    if folder is None:  # not a caching dispatcher any more: say nothing
        return True
    source = Path(_kernels.__file__).stat().st_mtime
    indexes = Path(folder).glob(f"{Path(_kernels.__file__).stem}.soft_forward_tasks-*.nbi")
    return any(index.stat().st_mtime >= source for index in indexes)


@contextmanager
def compile_notice(stream: TextIO, prog: str, who: str = "this command") -> Iterator[None]:
    """Around the first use of the learners: where their kernels are not cached, a line before
    (why nothing seems to happen) and, where ``who`` is this process, one after (how long it
    took). ``who``: what compiles them, e.g. "the first jobs" of a pool of processes."""
    if kernels_cached():
        yield
        return
    print(
        f"{prog}: note: {who} compiles the learners' kernels first, as on every machine's "
        f"first run ({COMPILE_TIME}; numba keeps them, and later runs load them in a second)",
        file=stream,
        flush=True,
    )
    started = time.monotonic()
    yield
    if who == "this command":
        print(
            f"{prog}: note: the kernels were compiled in {time.monotonic() - started:.0f} s",
            file=stream,
            flush=True,
        )
