"""The fixtures the study server's tests share (databases, the app, an update pool), from
tests/support/server.py, for every test folder: tests/app mirrors server/app room by room, and
tests/commands, tests/browser and tests/analysis drive the same server."""

import os
import sys
from collections.abc import Iterator

import pytest

from server import domains

pytest_plugins = ["tests.support.server", "tests.support.demo"]


@pytest.fixture(autouse=True)
def _study_environments_forgotten() -> Iterator[None]:
    """Each test starts with the study environments registered in this process that it found,
    whatever the test registered (a study's `demo` or `teach` run in process) and left."""
    before = domains.registered()
    yield
    for spec in domains.registered():
        if spec not in before:
            domains.unregister(spec.name)


def pytest_configure(config: pytest.Config) -> None:
    """Before any test, in the process that runs them or hands them to workers (``-n``): the
    learners' kernels compiled into numba's cache where it lacks them (a fresh clone), once.
    Otherwise the first tests that start a server wait minutes for its update processes to
    compile them, near their bounds on a slow machine, and workers side by side compile the
    same kernels each."""
    if hasattr(config, "workerinput"):  # a worker of ``-n``: its controller did it
        return
    from server.learners.compile_notice import COMPILE_TIME, kernels_cached

    if kernels_cached():
        return
    from server.app.updates.compiling import warm_up_in_processes

    processes = min(2, os.cpu_count() or 1)
    print(
        f"compiling the learners' kernels before the tests ({COMPILE_TIME}, shared by "
        f"{processes} processes)",
        file=sys.stderr,
    )
    seconds = warm_up_in_processes(processes)
    print(f"compiled in {seconds:.0f} s", file=sys.stderr)
