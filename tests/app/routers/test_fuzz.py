"""The API under schemathesis: requests generated from its OpenAPI schema (valid and invalid
bodies, parameters and path ids), sent over HTTP to the app served by uvicorn (one lifespan, as
``serve`` runs it) with a teaching participant's token and the admin token, on SQLite and
PostgreSQL. No answer may be a 5xx, and every answer must match the schema (its status code
documented, its body of the documented shape)."""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor

import httpx
import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings

from server.app.main import create_app
from server.app.participants.tokens import TOKEN_HEADER
from server.app.settings import Settings
from server.app.storage.db import Database
from server.app.study_file import StudyConfig
from tests.support.server import ADMIN_TOKEN, live, teaching_participant, wait_until_ready

# Bounded, so that the whole run (both backends) takes a few minutes.
EXAMPLES_PER_OPERATION = 30
CHECKS = [
    schemathesis.checks.not_a_server_error,
    schemathesis.checks.status_code_conformance,
    schemathesis.checks.content_type_conformance,
    schemathesis.checks.response_schema_conformance,
]
SENT: Counter[str] = Counter()


@pytest.fixture
def base_url(
    db: Database, settings: Settings, study: StudyConfig, executor: ProcessPoolExecutor
) -> Iterator[str]:
    # Over HTTP rather than in-process: schemathesis's in-process transport starts a second
    # lifespan on the app, whose new update queue answers /api/health 503 until it is warm.
    with live(create_app(settings, study, db=db, executor=executor)) as url:
        yield url


@pytest.fixture
def credentials(base_url: str) -> dict[str, str]:
    with httpx.Client(base_url=base_url, timeout=60) as client:
        wait_until_ready(client)  # a ready server: /api/health answers 503 while it starts
        participant, _ = teaching_participant(client)
    return {TOKEN_HEADER: participant.token, "Authorization": f"Bearer {ADMIN_TOKEN}"}


@pytest.fixture(scope="module", autouse=True)
def report() -> Iterator[None]:
    yield
    print(f"\nschemathesis: {SENT['requests']} requests, {SENT['5xx']} answered 5xx")


@pytest.mark.slow
@pytest.mark.parametrize("mode", list(schemathesis.GenerationMode), ids=str)
def test_no_request_gets_a_5xx_or_breaks_the_schema(
    base_url: str, credentials: dict[str, str], mode: schemathesis.GenerationMode
) -> None:
    api = schemathesis.openapi.from_url(f"{base_url}/openapi.json")
    operations = [result.ok() for result in api.get_all_operations()]
    assert len(operations) > 20
    for operation in operations:
        if mode == schemathesis.GenerationMode.NEGATIVE and not any(
            len(inputs) for inputs in (operation.path_parameters, operation.query, operation.body)
        ):
            continue  # nothing to make invalid

        @given(case=operation.as_strategy(generation_mode=mode))
        @settings(
            max_examples=EXAMPLES_PER_OPERATION,
            deadline=None,
            suppress_health_check=list(HealthCheck),
            derandomize=True,
            database=None,
        )
        def send(case: schemathesis.Case) -> None:
            response = case.call(
                base_url=base_url, headers={**credentials, **(case.headers or {})}, timeout=60
            )
            SENT["requests"] += 1
            SENT["5xx"] += response.status_code >= 500
            case.validate_response(response, checks=CHECKS)

        send()
