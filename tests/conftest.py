"""The fixtures the study server's tests share (databases, the app, an update pool), from
tests/support/server.py, for every test folder: tests/app mirrors server/app room by room, and
tests/commands, tests/browser and tests/analysis drive the same server."""

from collections.abc import Iterator

import pytest

from server import domains

pytest_plugins = ["tests.support.server"]


@pytest.fixture(autouse=True)
def _study_environments_forgotten() -> Iterator[None]:
    """Each test starts with the study environments registered in this process that it found,
    whatever the test registered (a study's `demo` or `teach` run in process) and left."""
    before = domains.registered()
    yield
    for spec in domains.registered():
        if spec not in before:
            domains.unregister(spec.name)
