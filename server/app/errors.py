"""Errors the API answers with a 4xx (or 503) and a clear message; nothing is changed."""

from __future__ import annotations


class ApiError(Exception):
    def __init__(self, status: int, message: str, headers: dict[str, str] | None = None) -> None:
        super().__init__(message)
        self.status = status
        self.message = message
        self.headers = headers


class TurnedAway(ApiError):
    """The arrival is refused (a repeat worker, or an arrival the study does not accept: 403;
    a worker who returned an assignment another worker holds now: 409)."""

    def __init__(self, title: str, message: str, status: int = 403) -> None:
        super().__init__(status, message)
        self.title = title


class LearnerBusy(Exception):
    """An agent step must wait for its own learner's pending update (index ``target``)."""

    def __init__(self, session_id: int, target: int) -> None:
        super().__init__(f"session {session_id} waits for update {target}")
        self.session_id = session_id
        self.target = target


class InvalidInput(ApiError):
    """A 422 for a value the request's schema allows but the study does not (an answer the
    question does not take): answered in the shape of FastAPI's own 422s, with ``loc``."""

    def __init__(self, loc: tuple[str | int, ...], message: str) -> None:
        super().__init__(422, message)
        self.loc = loc
