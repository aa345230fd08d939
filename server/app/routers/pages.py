"""``GET /study``: the entry URL the platforms open (MTurk in an iframe, Prolific, a lab).

A preview gets the preview page and creates nothing; an arrival the study refuses gets a page
that says why; an arrival sets the participant's cookie and gets the study page, which then
works through the JSON API (with the participant's new token in the page, for a browser that
keeps no cookie in the platform's iframe).
"""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from fastapi.responses import HTMLResponse
from pydantic import ValidationError

from server.app.deps import StateDep
from server.app.errors import ApiError, TurnedAway
from server.app.routers.common import arrive, notice, templates
from server.app.schemas import ArrivalRequest

router = APIRouter(tags=["pages"])

ARRIVAL_PARAMETERS = {field.alias or name for name, field in ArrivalRequest.model_fields.items()}


@router.get("/study", response_class=HTMLResponse)
def study_page(request: Request, state: StateDep) -> Response:
    # Platforms may append parameters of their own: only ours are read.
    params = {k: v for k, v in request.query_params.items() if k in ARRIVAL_PARAMETERS}
    try:
        body = ArrivalRequest.model_validate(params)
    except ValidationError as error:
        fields = ", ".join(str(e["loc"][0]) for e in error.errors())
        return notice(
            request, "This study link is not valid", f"Malformed parameter(s): {fields}.", 400
        )
    response = Response()
    try:
        arrival = arrive(state, body, request, response)
    except TurnedAway as refused:
        return notice(request, refused.title, refused.message, refused.status)
    except ApiError as error:
        return notice(request, "This study link is not valid", error.message, error.status)
    if arrival.preview:
        return templates.TemplateResponse(request, "preview.html", {"study": state.study.public()})
    # A new token is also given to the page itself, which sends it in the X-Participant-Token
    # header: in the platform's cross-site iframe the browser may keep no cookie. The page is
    # this participant's alone, so no cache may keep it.
    page = templates.TemplateResponse(
        request,
        "study.html",
        {"study": state.study.public(), "participant": arrival.participant, "token": arrival.token},
        headers={"Cache-Control": "no-store"},
    )
    for key, value in response.headers.items():
        if key == "set-cookie":
            page.headers.append(key, value)
    return page
