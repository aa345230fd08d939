"""FastAPI's OpenTelemetry instrumentation runs only with BAM_OPENTELEMETRY: off (the
default), a request does not look for OpenTelemetry's providers, which cost a tenth of a move's
CPU time on the server."""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor
from typing import Any

import pytest
from fastapi.testclient import TestClient
from opentelemetry import trace

from server.app.main import create_app
from server.app.storage.db import Database
from tests.support.server import make_settings, study_config


@pytest.mark.parametrize("opentelemetry", [False, True])
def test_requests_look_for_the_tracer_only_with_opentelemetry_on(
    db: Database,
    executor: ProcessPoolExecutor,
    monkeypatch: pytest.MonkeyPatch,
    opentelemetry: bool,
) -> None:
    looked: list[int] = []
    provider = trace.get_tracer_provider()

    def counted(*args: Any, **kwargs: Any) -> Any:
        looked.append(1)
        return provider

    monkeypatch.setattr(trace, "get_tracer_provider", counted)
    url = db.engine.url.render_as_string(hide_password=False)
    settings = make_settings(url, opentelemetry=opentelemetry)
    app = create_app(settings, study_config(), db=db, executor=executor)
    with TestClient(app) as client:
        looked.clear()
        for _ in range(3):
            assert client.get("/api/study").status_code == 200
    assert (len(looked) >= 3) is opentelemetry
    assert (len(looked) == 0) is not opentelemetry
