"""The replica's API: ``handle`` answers one request under ``/api/v1/`` from its route, and
``ReplicaTransport`` hands the study server's client's requests to it inside the process."""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any
from urllib.parse import parse_qs

import httpx
from sqlalchemy.orm import Session

from server.app.platforms.prolific_replica.base import (
    PROJECT_ID,
    WORKSPACE_ID,
    Refusal,
    StudyChange,
    Workspace,
    _study,
    _submission,
    error_body,
)
from server.app.platforms.prolific_replica.groups import (
    _group,
    create_group,
    group_members,
    group_view,
    list_groups,
)
from server.app.platforms.prolific_replica.hooks import (
    EVENT_TYPES,
    _subscription,
    confirm_subscription,
    create_secret,
    create_subscription,
    list_secrets,
    list_subscriptions,
    subscription_events,
    subscription_view,
)
from server.app.platforms.prolific_replica.messages import bulk_message, list_messages, send_message
from server.app.platforms.prolific_replica.money import (
    balance,
    pay_bonuses,
    reward_recommendations,
    set_up_bonuses,
    study_cost,
)
from server.app.platforms.prolific_replica.studies import (
    create_study,
    publish_due,
    transition_study,
    update_study,
)
from server.app.platforms.prolific_replica.submissions import (
    bulk_approve,
    list_submissions,
    submission_counts,
    transition_submission,
)
from server.app.platforms.prolific_replica.views import study_view, submission_detail
from server.app.storage.db import Database
from server.app.storage.models import utcnow

ROUTES: list[tuple[str, re.Pattern[str], str]] = [
    ("POST", re.compile(r"studies/"), "create_study"),
    ("GET", re.compile(r"studies/(?P<id>[0-9a-f]{24})/"), "get_study"),
    ("PATCH", re.compile(r"studies/(?P<id>[0-9a-f]{24})/"), "update_study"),
    ("POST", re.compile(r"studies/(?P<id>[0-9a-f]{24})/transition/"), "transition_study"),
    ("GET", re.compile(r"studies/(?P<id>[0-9a-f]{24})/submissions/counts/"), "submission_counts"),
    ("GET", re.compile(r"submissions/"), "list_submissions"),
    ("POST", re.compile(r"submissions/bulk-approve/"), "bulk_approve"),
    ("POST", re.compile(r"submissions/bonus-payments/"), "set_up_bonuses"),
    ("GET", re.compile(r"submissions/(?P<id>[0-9a-f]{24})/"), "get_submission"),
    ("POST", re.compile(r"submissions/(?P<id>[0-9a-f]{24})/transition/"), "transition_submission"),
    ("POST", re.compile(r"bulk-bonus-payments/(?P<id>[0-9a-f]{24})/pay/"), "pay_bonuses"),
    ("GET", re.compile(r"projects/(?P<id>[0-9a-f]{24})/"), "get_project"),
    ("GET", re.compile(r"workspaces/(?P<id>[0-9a-f]{24})/balance/"), "get_balance"),
    ("GET", re.compile(r"workspaces/"), "list_workspaces"),
    ("POST", re.compile(r"study-cost-calculator/"), "study_cost"),
    ("GET", re.compile(r"reward-recommendations/"), "reward_recommendations"),
    ("POST", re.compile(r"messages/"), "send_message"),
    ("GET", re.compile(r"messages/"), "list_messages"),
    ("POST", re.compile(r"messages/bulk/"), "bulk_message"),
    ("GET", re.compile(r"hooks/event-types/"), "event_types"),
    ("POST", re.compile(r"hooks/secrets/"), "create_secret"),
    ("GET", re.compile(r"hooks/secrets/"), "list_secrets"),
    ("POST", re.compile(r"hooks/subscriptions/"), "create_subscription"),
    ("GET", re.compile(r"hooks/subscriptions/"), "list_subscriptions"),
    ("GET", re.compile(r"hooks/subscriptions/(?P<id>[0-9a-f]{24})/"), "get_subscription"),
    ("POST", re.compile(r"hooks/subscriptions/(?P<id>[0-9a-f]{24})/"), "confirm_subscription"),
    (
        "GET",
        re.compile(r"hooks/subscriptions/(?P<id>[0-9a-f]{24})/events/"),
        "subscription_events",
    ),
    ("POST", re.compile(r"participant-groups/"), "create_group"),
    ("GET", re.compile(r"participant-groups/"), "list_groups"),
    ("GET", re.compile(r"participant-groups/(?P<id>[0-9a-f]{24})/"), "get_group"),
    *(
        (method, re.compile(r"participant-groups/(?P<id>[0-9a-f]{24})/participants/"), "members")
        for method in ("GET", "POST", "DELETE")
    ),
]


@dataclass(frozen=True)
class Call:
    """One request to an endpoint: its method, the id in its path ('' for none), its JSON
    body, its query, the replica's workspace, and the answer's own headers (None: not kept)."""

    method: str
    ident: str
    body: dict[str, Any]
    query: dict[str, str]
    workspace: Workspace
    headers: dict[str, str] | None


def _get_project(ident: str) -> tuple[int, Any]:
    if ident != PROJECT_ID:
        raise Refusal(404, f"Project {ident} not found.")
    return 200, {"id": PROJECT_ID, "title": "Rehearsals", "workspace": WORKSPACE_ID}


def _get_balance(s: Session, ident: str, workspace: Workspace) -> tuple[int, Any]:
    if ident != WORKSPACE_ID:
        raise Refusal(404, f"Workspace {ident} not found.")
    return 200, balance(s, workspace)


# Each endpoint of ``ROUTES`` but the two that change a study's status (``handle`` records
# those changes): what it answers, from the database session and the call.
ENDPOINTS: dict[str, Callable[[Session, Call], tuple[int, Any]]] = {
    "create_study": lambda s, c: create_study(s, c.body),
    "get_study": lambda s, c: (200, study_view(s, _study(s, c.ident))),
    "list_submissions": lambda s, c: list_submissions(s, c.query),
    "submission_counts": lambda s, c: submission_counts(s, c.ident),
    "bulk_approve": lambda s, c: bulk_approve(s, c.body),
    "set_up_bonuses": lambda s, c: set_up_bonuses(s, c.body),
    "get_submission": lambda s, c: (200, submission_detail(s, _submission(s, c.ident))),
    "transition_submission": lambda s, c: transition_submission(s, c.ident, c.body),
    "pay_bonuses": lambda s, c: pay_bonuses(s, c.ident),
    "get_project": lambda s, c: _get_project(c.ident),
    "get_balance": lambda s, c: _get_balance(s, c.ident, c.workspace),
    "list_workspaces": lambda s, c: (
        200,
        {"results": [{"id": WORKSPACE_ID, "title": "Rehearsals"}]},
    ),
    "study_cost": lambda s, c: study_cost(c.body),
    "reward_recommendations": lambda s, c: reward_recommendations(c.query),
    "send_message": lambda s, c: send_message(s, c.body),
    "list_messages": lambda s, c: list_messages(s, c.query),
    "bulk_message": lambda s, c: bulk_message(s, c.body),
    "event_types": lambda s, c: (200, {"results": [{"event_type": e} for e in EVENT_TYPES]}),
    "create_secret": lambda s, c: create_secret(s, c.body),
    "list_secrets": lambda s, c: list_secrets(s, c.query),
    "create_subscription": lambda s, c: create_subscription(s, c.body, c.headers),
    "list_subscriptions": lambda s, c: list_subscriptions(s, c.query),
    "get_subscription": lambda s, c: (200, subscription_view(_subscription(s, c.ident))),
    "confirm_subscription": lambda s, c: confirm_subscription(s, c.ident, c.body),
    "subscription_events": lambda s, c: subscription_events(s, c.ident, c.query),
    "create_group": lambda s, c: create_group(s, c.body),
    "list_groups": lambda s, c: list_groups(s, c.query),
    "get_group": lambda s, c: (200, group_view(s, _group(s, c.ident))),
    "members": lambda s, c: group_members(s, c.method, c.ident, c.body),
}
# The endpoints that change a study's status.
STUDY_CHANGES = {"update_study": update_study, "transition_study": transition_study}


def handle(
    db: Database,
    method: str,
    path: str,
    query: dict[str, str],
    raw: bytes,
    workspace: Workspace = Workspace(),
    changes: list[StudyChange] | None = None,
    headers: dict[str, str] | None = None,
) -> tuple[int, Any]:
    """Prolific's answer (status, JSON body) to one request under ``/api/v1/``; a study's change
    of status is added to ``changes`` (for its ``study.status.change`` webhook), the answer's
    own headers (a subscription's ``X-Hook-Secret``) to ``headers``."""
    path = path.lstrip("/")
    known = [(m, name, p.fullmatch(path)) for m, p, name in ROUTES]
    matches = [(m, name, found) for m, name, found in known if found]
    if not matches:
        return 404, error_body(404, f"No endpoint /api/v1/{path}.")
    chosen = [(name, found) for m, name, found in matches if m == method]
    if not chosen:
        return 405, error_body(405, f'Method "{method}" not allowed.')
    name, found = chosen[0]
    body: Any = {}
    if raw:
        try:
            body = json.loads(raw)
        except ValueError:
            return 400, error_body(400, "JSON parse error.")
    if not isinstance(body, dict):
        return 400, error_body(400, "The body must be a JSON object.")
    call = Call(method, found.groupdict().get("id", ""), body, query, workspace, headers)
    try:
        with db.write() as s:
            due = publish_due(s)
            if changes is not None:
                changes.extend(due)
            if name in STUDY_CHANGES:
                before = _study(s, call.ident).status
                answer = STUDY_CHANGES[name](s, call.ident, body)
                study = _study(s, call.ident)
                if changes is not None and study.status != before:
                    changes.append(StudyChange(study.id, study.status, utcnow()))
                return answer
            return ENDPOINTS[name](s, call)
    except Refusal as refused:
        return refused.status, error_body(refused.status, refused.detail)


class ReplicaTransport(httpx.BaseTransport):
    """The client's requests answered by the replica inside this process (no network): the
    same code runs as against Prolific, with the token checked as Prolific does."""

    def __init__(
        self,
        db: Database,
        token: str,
        prefix: str = "/prolific/api/v1/",
        workspace: Workspace = Workspace(),
    ) -> None:
        self.db = db
        self.token = token
        self.prefix = prefix
        self.workspace = workspace

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        headers: dict[str, str] = {}
        if request.headers.get("Authorization") != f"Token {self.token}":
            status, body = 401, error_body(401, "Invalid token.")
        else:
            path = request.url.path
            path = path[len(self.prefix) :] if path.startswith(self.prefix) else path
            query = {k: v[-1] for k, v in parse_qs(request.url.query.decode()).items()}
            status, body = handle(
                self.db, request.method, path, query, request.read(), self.workspace, None, headers
            )
        content = b"" if body is None else json.dumps(body).encode()
        return httpx.Response(
            status, content=content, headers={"Content-Type": "application/json", **headers}
        )
