"""Prolific's API (https://api.prolific.com/api/v1, docs.prolific.com/api-reference) as the
study server uses it, and Prolific behind ``ReviewBackend``.

``ProlificClient`` is a small httpx client: the token goes in ``Authorization: Token ...`` and
nowhere else (never logged, never in an error message); a 429 or a 5xx is retried with
exponential back-off; a 4xx becomes ``ProlificRefused`` with Prolific's own message. Every call
is scoped to one study: submissions are listed with ``?study=`` (never the account's whole
list), and a submission or bonus of another study is refused here before anything is sent.

``ProlificClient`` (about 370 lines) has one method per call of Prolific's API that the
server makes, each beside the others it shares its retries and scoping with.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from datetime import timedelta
from typing import Any

import httpx

from server.app.platforms.review import (
    Reviewed,
    ReviewRefused,
    ReviewUnavailable,
)
from server.app.storage.vocabulary import ReviewDecision
from server.app.study_file import Completion, ProlificStudy, StudyConfig

# Prolific's submission statuses (the submission object's ``status``).
SUBMISSION_STATUSES = (
    "RESERVED",
    "ACTIVE",
    "TIMED-OUT",
    "AWAITING REVIEW",
    "APPROVED",
    "RETURNED",
    "REJECTED",
    "SCREENED OUT",
    "PARTIALLY APPROVED",
)
# Prolific's study statuses (the study object's ``status``; ``study.status.change``).
STUDY_STATUSES = (
    "UNPUBLISHED",
    "PUBLISHING",
    "SCHEDULED",
    "ACTIVE",
    "PAUSED",
    "AWAITING REVIEW",
    "COMPLETED",
)
# The statuses that are a decision, as ours.
PROLIFIC_DECISIONS = {"APPROVED": ReviewDecision.APPROVED, "REJECTED": ReviewDecision.REJECTED}
RETRIED = frozenset({429, 500, 502, 503, 504})
# Shown by Prolific to a participant whose device failed our check (INCOMPATIBLE_DEVICE).
INCOMPATIBLE_DEVICE_REASON = (
    "Your device or window could not run the study (it needs arrow keys and a larger window): "
    "please return the study."
)
# Shown by Prolific to a participant who declined consent or withdrew (our NO_CONSENT code).
NO_CONSENT_REASON = (
    "You did not consent to take part, or you withdrew your consent: please return the study."
)


class ProlificRefused(ReviewRefused):
    """Prolific answered 4xx: the request was not carried out."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


class ProlificUnavailable(ReviewUnavailable):
    """Prolific could not be reached or kept answering 429 or 5xx."""


def _message(response: httpx.Response) -> str:
    """Prolific's explanation of a refusal (its error body, or the status line)."""
    try:
        body = response.json()
    except ValueError:
        return response.text[:300] or response.reason_phrase
    error = body.get("error", body) if isinstance(body, dict) else body
    if isinstance(error, dict):
        detail = error.get("detail") or error.get("title") or error
        return detail if isinstance(detail, str) else str(detail)[:300]
    return str(error)[:300]


class ProlificClient:
    """The calls the study server makes, each scoped to ``study_id`` where Prolific allows."""

    def __init__(
        self,
        base_url: str,
        token: str,
        *,
        attempts: int = 5,
        first_wait: float = 0.5,
        timeout: float = 30.0,
        transport: httpx.BaseTransport | None = None,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        self._http = httpx.Client(
            base_url=base_url.rstrip("/") + "/",
            headers={"Authorization": f"Token {token}", "Accept": "application/json"},
            timeout=timeout,
            transport=transport,
        )
        self.attempts = attempts
        self.first_wait = first_wait
        self.sleep = sleep

    def __repr__(self) -> str:  # no token in any representation
        return f"ProlificClient({str(self._http.base_url)!r})"

    def close(self) -> None:
        self._http.close()

    def request(
        self,
        method: str,
        path: str,
        *,
        retry: bool = True,
        creates: bool = False,
        with_status: bool = False,
        with_headers: bool = False,
        **kwargs: Any,
    ) -> Any:
        """Prolific's JSON answer (None for an empty one; with ``with_status``, the answer's
        status code and it; with ``with_headers``, the answer's headers and it). ``retry=False`` for a call that must
        not be sent twice (``pay``): a failure then is reported, never resent. ``creates`` for
        a call that makes something (a draft study, a bonus set-up): resent only where
        Prolific cannot have acted (a 429, a connection that never opened); after a 5xx or a
        lost answer it may exist, so the failure is reported, not a second one made."""
        wait = self.first_wait
        maybe_made = " (it may have been made: look on Prolific before sending it again)"
        for attempt in range(1, self.attempts + 1):
            last = attempt == self.attempts or not retry
            try:
                response = self._http.request(method, path.lstrip("/"), **kwargs)
            except httpx.HTTPError as error:
                unsent = isinstance(error, httpx.ConnectError)
                if last or (creates and not unsent):
                    raise ProlificUnavailable(
                        f"Prolific ({self._http.base_url}) did not answer {method} "
                        f"/{path.lstrip('/')}: {type(error).__name__}"
                        + (maybe_made if creates and not unsent else "")
                    ) from None
            else:
                if response.status_code in RETRIED:
                    acted = creates and response.status_code != 429
                    if last or acted:
                        raise ProlificUnavailable(
                            f"Prolific answered {response.status_code} to {method} "
                            f"/{path.lstrip('/')}: {_message(response)}"
                            + (maybe_made if acted else "")
                        )
                    after = response.headers.get("Retry-After", "")
                    if after.isdigit():
                        wait = max(wait, min(float(after), 60.0))
                elif response.status_code >= 400:
                    raise ProlificRefused(
                        response.status_code,
                        f"Prolific refused {method} /{path.lstrip('/')} "
                        f"({response.status_code}): {_message(response)}",
                    )
                else:
                    answer = response.json() if response.content else None
                    if with_headers:
                        return response.headers, answer
                    return (response.status_code, answer) if with_status else answer
            self.sleep(wait)
            wait *= 2
        raise AssertionError("unreachable")  # pragma: no cover

    # -- studies --------------------------------------------------------------------------
    def create_study(self, fields: dict[str, Any]) -> dict[str, Any]:
        return dict(self.request("POST", "studies/", json=fields, creates=True))

    def get_study(self, study_id: str) -> dict[str, Any]:
        return dict(self.request("GET", f"studies/{study_id}/"))

    def transition_study(self, study_id: str, action: str) -> dict[str, Any]:
        return dict(
            self.request("POST", f"studies/{study_id}/transition/", json={"action": action})
        )

    def set_places(self, study_id: str, places: int) -> dict[str, Any]:
        return dict(
            self.request("PATCH", f"studies/{study_id}/", json={"total_available_places": places})
        )

    def set_max_concurrent(self, study_id: str, limit: int) -> dict[str, Any]:
        """The study's ``max_concurrent_submissions`` (its ``submissions_config``, which a
        published study's PATCH takes)."""
        return dict(
            self.request(
                "PATCH",
                f"studies/{study_id}/",
                json={"submissions_config": {"max_concurrent_submissions": limit}},
            )
        )

    def schedule_publish(self, study_id: str, publish_at: str) -> dict[str, Any]:
        """Publish the draft at ``publish_at`` (ISO 8601): Prolific's SCHEDULE_PUBLISH."""
        return dict(
            self.request(
                "POST",
                f"studies/{study_id}/transition/",
                json={"action": "SCHEDULE_PUBLISH", "publish_at": publish_at},
            )
        )

    # -- webhooks -------------------------------------------------------------------------
    def create_hook_secret(self, workspace_id: str) -> str:
        """A new signing secret for the workspace's webhooks (it replaces the old one)."""
        made = self.request("POST", "hooks/secrets/", json={"workspace_id": workspace_id})
        value = made.get("value") if isinstance(made, dict) else None
        if not isinstance(value, str) or not value:
            raise ProlificUnavailable("Prolific's answer to POST /hooks/secrets/ has no value")
        return value

    def subscribe(self, workspace_id: str, event_type: str, target_url: str) -> dict[str, Any]:
        """Subscribe ``target_url`` to the event type and confirm it with the ``X-Hook-Secret``
        Prolific answered; the subscription as Prolific confirmed it."""
        headers, made = self.request(
            "POST",
            "hooks/subscriptions/",
            json={"event_type": event_type, "target_url": target_url, "workspace_id": workspace_id},
            creates=True,
            with_headers=True,
        )
        # The reference gives a list (``results``), its guide an object with ``id``.
        listed = made.get("results") if isinstance(made, dict) else None
        detail = listed[0] if isinstance(listed, list) and listed else made
        subscription = detail.get("id") if isinstance(detail, dict) else None
        confirmation = headers.get("X-Hook-Secret")
        if not isinstance(subscription, str) or not confirmation:
            raise ProlificUnavailable(
                f"Prolific's answer to subscribing {event_type} has no subscription id or "
                "X-Hook-Secret to confirm it with"
            )
        return dict(
            self.request(
                "POST", f"hooks/subscriptions/{subscription}/", json={"secret": confirmation}
            )
        )

    def subscriptions(self, workspace_id: str) -> list[dict[str, Any]]:
        """The workspace's enabled subscriptions."""
        body = self.request("GET", "hooks/subscriptions/", params={"workspace_id": workspace_id})
        return list(body.get("results", []))

    def hook_events(self, subscription_id: str) -> list[dict[str, Any]]:
        """The deliveries of the subscription's events (each with its ``status``)."""
        body = self.request("GET", f"hooks/subscriptions/{subscription_id}/events/")
        return list(body.get("results", []))

    # -- participant groups ---------------------------------------------------------------
    def workspaces(self) -> list[dict[str, Any]]:
        """The workspaces the account is a member of (``GET /workspaces/``)."""
        return list(self.request("GET", "workspaces/").get("results", []))

    def participant_group(self, workspace_id: str, name: str) -> str:
        """The id of the workspace's participant group called ``name``, made if it has none."""
        listed = self.request(
            "GET", "participant-groups/", params={"workspace_id": workspace_id}
        ).get("results", [])
        for group in listed:
            if group.get("name") == name and not group.get("is_deleted"):
                return str(group["id"])
        made = self.request(
            "POST",
            "participant-groups/",
            json={"workspace_id": workspace_id, "name": name},
            creates=True,
        )
        return str(made["id"])

    def group_members(self, group_id: str) -> list[str]:
        body = self.request("GET", f"participant-groups/{group_id}/participants/")
        return [str(m["participant_id"]) for m in body.get("results", [])]

    def add_to_group(self, group_id: str, participant_ids: list[str]) -> list[str]:
        """Add participants to the group (members already in are left); its members."""
        body = self.request(
            "POST",
            f"participant-groups/{group_id}/participants/",
            json={"participant_ids": participant_ids},
        )
        return [str(m["participant_id"]) for m in body.get("results", [])]

    # -- money ----------------------------------------------------------------------------
    def workspace_of(self, study: dict[str, Any]) -> str:
        """The id of the workspace whose funds pay the study (through its project)."""
        project = study.get("project")
        if not isinstance(project, str) or not project:
            raise ProlificUnavailable(
                f"Prolific's study {study.get('id')} names no project, so its workspace (and "
                "balance) cannot be found"
            )
        workspace = self.request("GET", f"projects/{project}/").get("workspace")
        if not isinstance(workspace, str) or not workspace:
            raise ProlificUnavailable(f"Prolific's project {project} names no workspace")
        return workspace

    def balance(self, workspace_id: str) -> dict[str, Any]:
        """The workspace's balance: ``currency_code``, ``total_balance`` and
        ``available_balance`` (in cents: what active studies hold is not available)."""
        return dict(self.request("GET", f"workspaces/{workspace_id}/balance/"))

    def study_cost(self, reward_cents: int, places: int) -> int:
        """What ``places`` places at ``reward_cents`` cost, with Prolific's fees and VAT, in
        cents of the workspace's currency."""
        body = self.request(
            "POST",
            "study-cost-calculator/",
            json={"reward": reward_cents, "total_available_places": places},
        )
        return round(body["total_cost"])

    def least_hourly_reward(self, workspace_id: str, currency: str) -> int | None:
        """Prolific's minimum hourly reward for the workspace, in cents (the first of its
        reward recommendations, the most recent); None when it gives none."""
        listed = self.request(
            "GET",
            "reward-recommendations/",
            params={"workspace_id": workspace_id, "currency": currency},
        )
        if isinstance(listed, list) and listed and isinstance(listed[0], dict):
            least = listed[0].get("min_reward_per_hour")
            if isinstance(least, int) and not isinstance(least, bool) and least > 0:
                return least
        return None

    # -- submissions ----------------------------------------------------------------------
    def submissions(self, study_id: str, page_size: int = 100) -> Iterator[dict[str, Any]]:
        """Every submission of the study, page by page."""
        page = 1
        while True:
            body = self.request(
                "GET",
                "submissions/",
                # In the order they started: a page stays put while submissions arrive.
                params={
                    "study": study_id,
                    "page": page,
                    "page_size": page_size,
                    "ordering": "started_at",
                },
            )
            yield from body.get("results", [])
            links = body.get("_links", {})
            following = links.get("next", {}) if isinstance(links, dict) else {}
            if not (isinstance(following, dict) and following.get("href")):
                return
            page += 1

    def submission_counts(self, study_id: str) -> dict[str, int]:
        """The study's submissions per status, and their ``TOTAL``, in one call
        (``GET /studies/{id}/submissions/counts/``)."""
        body = self.request("GET", f"studies/{study_id}/submissions/counts/")
        if not isinstance(body, dict) or not all(
            isinstance(n, (int, float)) and not isinstance(n, bool) for n in body.values()
        ):
            raise ProlificUnavailable(
                f"Prolific's counts of study {study_id}'s submissions are not numbers per status"
            )
        return {str(status): round(n) for status, n in body.items()}

    def submission(self, study_id: str, submission_id: str) -> dict[str, Any]:
        body = dict(self.request("GET", f"submissions/{submission_id}/"))
        if body.get("study_id") not in (None, study_id):
            raise ProlificRefused(
                403, f"submission {submission_id} is not a submission of study {study_id}"
            )
        return body

    def transition_submission(
        self, study_id: str, submission_id: str, action: str, **fields: Any
    ) -> dict[str, Any]:
        self.submission(study_id, submission_id)
        return dict(
            self.request(
                "POST",
                f"submissions/{submission_id}/transition/",
                json={"action": action, **fields},
            )
        )

    def bulk_approve(self, study_id: str, submission_ids: list[str]) -> None:
        """Approve many submissions of the study (Prolific recommends at most 1,000 a call)."""
        for start in range(0, len(submission_ids), 1000):
            self.request(
                "POST",
                "submissions/bulk-approve/",
                json={"submission_ids": submission_ids[start : start + 1000]},
            )

    # -- messages -------------------------------------------------------------------------
    def send_message(self, study_id: str, recipients: list[str], body: str) -> int:
        """Send ``body`` about the study to each participant of ``recipients``: one with
        ``POST /messages/``, several with ``POST /messages/bulk/``; Prolific's status code
        (204: sent). Resent only where Prolific cannot have sent it (a 429, no connection)."""
        if len(recipients) == 1:
            status, _ = self.request(
                "POST",
                "messages/",
                json={"recipient_id": recipients[0], "body": body, "study_id": study_id},
                creates=True,
                with_status=True,
            )
        else:
            status, _ = self.request(
                "POST",
                "messages/bulk/",
                json={"ids": recipients, "body": body, "study_id": study_id},
                creates=True,
                with_status=True,
            )
        return int(status)

    def messages_with(self, user_id: str) -> list[dict[str, Any]]:
        """The messages between the researcher and ``user_id`` (Prolific keeps 30 days)."""
        return list(self.request("GET", "messages/", params={"user_id": user_id})["results"])

    # -- bonuses --------------------------------------------------------------------------
    def set_up_bonuses(self, study_id: str, bonuses: list[tuple[str, str]]) -> dict[str, Any]:
        """Set up (not pay) bonuses: ``(participant or submission id, amount in the study's
        currency)``; Prolific's answer has the set-up's ``id`` that ``pay_bonuses`` pays."""
        csv = "".join(f"{who},{amount}\n" for who, amount in bonuses)
        return dict(
            self.request(
                "POST",
                "submissions/bonus-payments/",
                json={"study_id": study_id, "csv_bonuses": csv},
                creates=True,  # a 5xx may have set one up: not a second one unasked
            )
        )

    def pay_bonuses(self, setup_id: str) -> None:
        """Pay a set-up: sent once, never retried (Prolific's pay is not idempotent)."""
        self.request("POST", f"bulk-bonus-payments/{setup_id}/pay/", retry=False)

    def bonus_payments(self, study_id: str, submission_id: str) -> list[int]:
        """The bonuses Prolific lists as paid on the submission, in cents (its
        ``bonus_payments``: what settles a bonus whose pay failed after it may have paid)."""
        listed = self.submission(study_id, submission_id).get("bonus_payments")
        if not isinstance(listed, list) or not all(
            isinstance(c, (int, float)) and not isinstance(c, bool) for c in listed
        ):
            raise ProlificUnavailable(
                f"Prolific's submission {submission_id} has no list of bonus_payments to "
                "settle a bonus by"
            )
        return [round(c) for c in listed]


class ProlificBackend:
    """Prolific's API behind ``ReviewBackend`` (``BAM_REVIEW_BACKEND=prolific``, or the local
    replica's API for a rehearsal)."""

    platform = "prolific"
    repeat_pay_is_safe = False  # Prolific's pay pays again
    token_memory: timedelta | None = None  # (no request token: a bonus is paid once, by its set-up)

    def __init__(self, client: ProlificClient, currency: str, name: str = "prolific") -> None:
        self.client = client
        self.currency = currency
        self.name = name
        self._currencies: dict[str, str] = {}  # study id -> its workspace's currency

    def _check_currency(self, study_id: str) -> None:
        """Refuse a bonus in another currency than the study's workspace pays in (Prolific
        reads a bonus's amount in it): the currency is read once per study."""
        currency = self._currencies.get(study_id)
        if currency is None:
            workspace = self.client.workspace_of(self.client.get_study(study_id))
            currency = str(self.client.balance(workspace).get("currency_code"))
            self._currencies[study_id] = currency
        if currency != self.currency:
            raise ReviewRefused(
                f"study {study_id}'s workspace pays in {currency}, but BAM_PROLIFIC_CURRENCY is "
                f"{self.currency}: Prolific would read the bonus's amount in {currency}. Set "
                f"BAM_PROLIFIC_CURRENCY={currency}; nothing was sent"
            )

    @staticmethod
    def _study(who: Reviewed) -> str:
        if not who.study_id:
            raise ReviewRefused(f"participant {who.participant_id} has no Prolific STUDY_ID")
        return who.study_id

    def approve(self, who: Reviewed, message: str | None) -> None:
        self.client.transition_submission(self._study(who), who.platform_submission_id, "APPROVE")

    def reject(self, who: Reviewed, message: str, category: str | None) -> None:
        self.client.transition_submission(
            self._study(who),
            who.platform_submission_id,
            "REJECT",
            message=message,
            rejection_category=category,
        )

    def decision_of(self, who: Reviewed) -> ReviewDecision | None:
        status = self.client.submission(self._study(who), who.platform_submission_id).get("status")
        return PROLIFIC_DECISIONS.get(str(status))

    def set_up_bonus(self, who: Reviewed, amount: str, reason: str) -> str | None:
        self._check_currency(self._study(who))
        made = self.client.set_up_bonuses(self._study(who), [(who.platform_participant_id, amount)])
        return str(made["id"])

    def pay_bonus(
        self, who: Reviewed, amount: str, reason: str, token: str, setup_id: str | None
    ) -> None:
        if setup_id is None:
            raise ReviewRefused(f"bonus {token} has no set-up on Prolific to pay")
        self.client.pay_bonuses(setup_id)

    def bonuses_paid(self, who: Reviewed) -> list[int] | None:
        return self.client.bonus_payments(self._study(who), who.platform_submission_id)


def draft_study(
    study: StudyConfig,
    max_concurrent: int,
    base_url: str | None = None,
    groups: dict[str, str] | None = None,
) -> dict[str, Any]:
    """The body of ``POST /studies/`` for the study file's ``[prolific]`` table: the study link
    of ``base_url`` (default: the public address) with Prolific's placeholders, the study's
    completion codes (COMPLETED for manual review; NO_CONSENT and INCOMPATIBLE_DEVICE asking
    for a return), the reward in cents, desktop only (the teaching page needs arrow keys), and
    at most ``max_concurrent`` participants at once (what the server can serve). ``groups``:
    the id of each participant group the table names (``family_group``, ``follow_up_group``,
    ``only_group``), by name: the family's is blocked and joined, the follow-up's joined, the
    only group's allowed."""
    prolific = study.prolific
    completion = study.completion
    if prolific is None:
        raise ValueError("the study file has no [prolific] table")
    if completion.mode != "prolific" or completion.prolific_code is None:
        raise ValueError(
            f'the study\'s completion mode is "{completion.mode}": a Prolific study needs '
            '[completion] mode = "prolific" with prolific_code'
        )
    if max_concurrent < 1:
        raise ValueError("max_concurrent_submissions must be at least 1")
    codes = _completion_codes(completion)
    fields: dict[str, Any] = {
        "name": prolific.name,
        "internal_name": study.title,
        "description": prolific.description,
        "external_study_url": prolific.study_link(base_url),
        "prolific_id_option": "url_parameters",
        "completion_codes": codes,
        "total_available_places": prolific.places,
        "reward": prolific.reward_cents,
        "estimated_completion_time": prolific.estimated_minutes,
        "maximum_allowed_time": prolific.maximum_minutes,
        "device_compatibility": ["desktop"],
        "submissions_config": {"max_concurrent_submissions": max_concurrent},
    }
    groups = groups or {}
    filters = _filters(prolific, groups)
    # The finishers (the COMPLETED code) join the family's group and the follow-up's.
    joined = dict.fromkeys(
        groups[name] for name in (prolific.family_group, prolific.follow_up_group) if name
    )
    codes[0]["actions"] += [
        {"action": "ADD_TO_PARTICIPANT_GROUP", "participant_group": group} for group in joined
    ]
    if filters:
        fields["filters"] = filters
    return fields


def _completion_codes(completion: Completion) -> list[dict[str, Any]]:
    """The study's completion codes: COMPLETED for manual review (first), and NO_CONSENT and
    INCOMPATIBLE_DEVICE, where the study file gives them, asking for a return."""
    assert completion.prolific_code is not None
    codes: list[dict[str, Any]] = [
        {
            "code": completion.prolific_code,
            "code_type": "COMPLETED",
            "actor": "participant",
            "actions": [{"action": "MANUALLY_REVIEW"}],
        }
    ]
    if completion.prolific_no_consent_code is not None:
        codes.append(
            {
                "code": completion.prolific_no_consent_code,
                "code_type": "NO_CONSENT",
                "actor": "participant",
                "actions": [{"action": "REQUEST_RETURN", "return_reason": NO_CONSENT_REASON}],
            }
        )
    if completion.prolific_incompatible_device_code is not None:
        codes.append(
            {
                "code": completion.prolific_incompatible_device_code,
                "code_type": "INCOMPATIBLE_DEVICE",
                "actor": "participant",
                "actions": [
                    {"action": "REQUEST_RETURN", "return_reason": INCOMPATIBLE_DEVICE_REASON}
                ],
            }
        )
    return codes


def _filters(prolific: ProlificStudy, groups: dict[str, str]) -> list[dict[str, Any]]:
    """Who may not take part: the studies of ``previous_studies_blocklist``, the family's
    group; and who alone may: the only group (a ValueError for a group without its id)."""
    filters: list[dict[str, Any]] = []
    if prolific.previous_studies_blocklist:
        filters.append(
            {
                "filter_id": "previous_studies_blocklist",
                "selected_values": list(prolific.previous_studies_blocklist),
            }
        )
    named = (prolific.family_group, prolific.follow_up_group, prolific.only_group)
    missing = [name for name in named if name is not None and name not in groups]
    if missing:
        raise ValueError(f"no participant group id for {', '.join(missing)}")
    if prolific.family_group is not None:
        filters.append(
            {
                "filter_id": "participant_group_blocklist",
                "selected_values": [groups[prolific.family_group]],
            }
        )
    if prolific.only_group is not None:
        filters.append(
            {
                "filter_id": "participant_group_allowlist",
                "selected_values": [groups[prolific.only_group]],
            }
        )
    return filters
