"""Dependencies shared by the routers, declared once (async: FastAPI would run plain functions
in its thread pool, a thread handoff per dependency and request)."""

from __future__ import annotations

import secrets
from typing import Annotated

from fastapi import Depends, Header, Path, Request

from server.app.errors import ApiError
from server.app.flow import TOKEN_HEADER
from server.app.state import ServerState


async def get_state(request: Request) -> ServerState:
    state: ServerState = request.app.state.server
    return state


StateDep = Annotated[ServerState, Depends(get_state)]

# Ids in paths: a row id of the database (PostgreSQL's integer is 32-bit), so that a larger
# number is refused here and never reaches the database driver.
MAX_ROW_ID = 2**31 - 1
RowId = Annotated[int, Path(ge=1, le=MAX_ROW_ID, description="A row id.")]


async def participant_token(
    request: Request,
    state: StateDep,
    token: Annotated[str | None, Header(alias=TOKEN_HEADER)] = None,
) -> str | None:
    """The participant's token: the header (HTTP clients) or the cookie (the browser)."""
    return token or request.cookies.get(state.settings.cookie_name)


TokenDep = Annotated[str | None, Depends(participant_token)]


async def require_admin(
    state: StateDep, authorization: Annotated[str | None, Header()] = None
) -> None:
    expected = state.settings.admin_token
    if expected is None or not expected.get_secret_value():
        raise ApiError(503, "the admin API is disabled: set BAM_ADMIN_TOKEN")
    scheme, _, given = (authorization or "").partition(" ")
    if scheme.lower() != "bearer" or not secrets.compare_digest(
        given.encode(), expected.get_secret_value().encode()
    ):
        raise ApiError(401, "admin token missing or wrong", headers={"WWW-Authenticate": "Bearer"})


AdminDep = Depends(require_admin)
