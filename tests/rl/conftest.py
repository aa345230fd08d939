"""The study server's fixtures (a fresh database per test on SQLite and on PostgreSQL, the app
with its update processes) for the dataset export's tests."""

from tests.support.server import (  # noqa: F401
    client,
    database_url,
    db,
    executor,
    settings,
    study,
)
