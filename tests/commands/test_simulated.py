"""The simulated participants' own bookkeeping: a request's latency is what a person would wait,
from its first attempt, and the requests that needed a retry are counted."""

from __future__ import annotations

import time
from typing import Any

from server.commands.simulated import LightResponse, SimulatedParticipant, TeachingPlan


class FlakyClient:
    """Answers each request only at its third attempt: the first two fail slowly (a lost
    connection, then a server that is restarting)."""

    def __init__(self, attempt_seconds: float) -> None:
        self.attempt_seconds = attempt_seconds
        self.attempts = 0

    def request(self, method: str, path: str, json: Any = None, headers: Any = None) -> Any:
        self.attempts += 1
        time.sleep(self.attempt_seconds)
        if self.attempts % 3 == 1:
            raise ConnectionResetError("connection lost")
        if self.attempts % 3 == 2:
            return LightResponse(503, {}, b"restarting")
        return LightResponse(200, {}, b'{"ok": true}')


def test_a_retried_request_is_timed_from_its_first_attempt_and_counted() -> None:
    attempt_seconds = 0.1
    client = FlakyClient(attempt_seconds)
    participant = SimulatedParticipant(
        "http://127.0.0.1:1",
        0,
        seed=0,
        plan=TeachingPlan(retry_seconds=10),
        client=client,  # type: ignore[arg-type]
    )
    assert participant.request("GET", "/api/participant", "read_participant") == {"ok": True}
    assert participant.request("GET", "/api/participant", "read_participant") == {"ok": True}

    run = participant.run
    assert client.attempts == 6
    assert run.retries == 4  # attempts sent again
    assert run.retried_requests == 2  # requests that needed them
    # Three attempts and two back-offs each, not only the last attempt.
    latencies = run.latencies["read_participant"]
    assert len(latencies) == 2
    assert all(latency >= 3 * attempt_seconds for latency in latencies)
    assert run.retried_latencies == latencies
