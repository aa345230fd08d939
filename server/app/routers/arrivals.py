"""Arrival at the study over the JSON API (the simulated participants, HTTP clients).

The browser arrives through ``GET /study`` (``pages.py``), with the same rules: an MTurk preview
creates nothing; MTurk and Prolific participants are keyed on (worker, assignment) and resumed
when they arrive again, with a new token if their cookie is gone; a worker with another
participation (of any status but returned or declined) is turned away unless the study allows
repeats.
"""

from __future__ import annotations

from fastapi import APIRouter, Request, Response, status

from server.app.deps import StateDep
from server.app.routers.common import arrive
from server.app.schemas import ArrivalRequest, ArrivalResponse

router = APIRouter(prefix="/api/arrivals", tags=["participants"])


@router.post(
    "",
    response_model=ArrivalResponse,
    responses={
        201: {"description": "A new participant."},
    },
)
def create_arrival(
    body: ArrivalRequest, request: Request, response: Response, state: StateDep
) -> ArrivalResponse:
    """Arrive with the platform's parameters (none in a lab). The token is returned once and
    set as a cookie; send it back in the X-Participant-Token header or the cookie."""
    answer = arrive(state, body, request, response)
    if answer.participant is not None and not answer.resumed:
        response.status_code = status.HTTP_201_CREATED
    return answer
