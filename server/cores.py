"""How many cores this process may use: the one figure that sizes the study server's update
threads, a simulation's pool and the benchmarks' defaults. Imports nothing heavy, so that
settings and command-line help can use it."""

from __future__ import annotations

import os


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity, which a container's cpuset
    narrows; ``os.cpu_count()`` counts the host's)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def share_threads(threads: int, sharers: int) -> int:
    """Each one's share of ``threads`` among ``sharers`` busy at once, at least one: so that
    they do not put more threads than cores to work (two study-server updates with two planner
    threads each on two cores did fewer updates and made longer waits, measured)."""
    return max(1, threads // max(1, sharers))
