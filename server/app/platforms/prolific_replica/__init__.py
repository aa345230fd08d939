"""The local Prolific replica's API: the subset of Prolific's REST API (``/api/v1``) that the
study server's client uses, at the same paths, with the same fields, statuses, status codes
and refusals, keeping its state in the database (``replica_models``).

``handle`` answers one request; the router (``routers/prolific.py``) serves it over HTTP at
``/prolific/api/v1/...``, and ``ReplicaTransport`` hands the client's requests to it inside the
server (the dashboard's reviews on a rehearsal). As on Prolific:

- a study is made as a draft (UNPUBLISHED), refused for the fields Prolific refuses (completion
  codes and their actions, devices, filters, submissions_config, times), and published, paused
  and started with transitions; after publishing its places can only go up, and at most its
  max_concurrent_submissions take part at once;
- submissions are listed for one study (``?study=`` is required), page by page, and counted
  per status (``/studies/{id}/submissions/counts/``);
- a completion code with the REQUEST_RETURN action (our NO_CONSENT code) completes the
  submission (AWAITING REVIEW) with ``return_requested`` set; it is RETURNED only if the
  participant then returns it (``routers/prolific.py``);
- a submission is approved or rejected once it is AWAITING REVIEW (a TIMED-OUT one may be
  approved too); a rejection needs one of Prolific's categories and a message of at least 100
  characters (400 otherwise); the same transition sent again is ignored (the endpoint is
  idempotent);
- bonuses are set up (``csv_bonuses``: participant or submission id, amount in the currency)
  and paid with ``pay``, which is not idempotent: a second ``pay`` pays again; a submission
  lists the bonuses paid on it (``bonus_payments``);
- messages (``POST /messages/``, ``/messages/bulk/``) go only to participants with a
  submission in the study named, are kept, and are listed with ``GET /messages/?user_id=``;
- the one workspace (``Workspace``: its currency, the funds put in it) has a balance that the
  rewards of approved submissions and the bonuses paid take from, with Prolific's fee, and that
  published studies hold their places' cost from; the study cost calculator and the reward
  recommendations answer as Prolific's;
- a draft can be scheduled (SCHEDULE_PUBLISH with a ``publish_at`` in the future; published at
  that time) and a published study's PATCH takes its places, ``internal_name`` and
  ``submissions_config``;
- webhooks: the workspace's one signing secret (``POST /hooks/secrets/``, a new one replaces
  the old; made by the replica itself when it first signs an event), subscriptions made
  disabled with an ``X-Hook-Secret`` that confirms them, and each delivery recorded with its
  status (PENDING, SUCCEEDED, FAILED); with no subscription at all, events go to this server's
  own webhook (``routers/prolific.py``), so a rehearsal needs no setting;
- participant groups: made, listed, joined and left through the API or by a completion code's
  ADD_TO_PARTICIPANT_GROUP / REMOVE_FROM_PARTICIPANT_GROUP, and the study filters
  ``participant_group_blocklist``, ``participant_group_allowlist`` and
  ``previous_studies_blocklist`` keep out whom they name.

One module per part of Prolific's API: ``studies``, ``submissions``, ``money`` (the balance and
bonuses), ``messages``, ``hooks``, ``groups``; ``views`` shows studies and submissions,
``base`` holds what they share and ``api`` routes a request to them. A name with a leading
underscore is the package's own.
"""

from __future__ import annotations

from server.app.platforms.prolific_replica.api import (
    ENDPOINTS,
    ROUTES,
    STUDY_CHANGES,
    Call,
    ReplicaTransport,
    handle,
)
from server.app.platforms.prolific_replica.base import (
    PLACEHOLDERS,
    PROJECT_ID,
    REPLICA_PATH,
    WORKSPACE_ID,
    Refusal,
    StudyChange,
    Workspace,
    completion_url,
    error_body,
    is_replica_study,
    new_id,
    workspace_of,
)
from server.app.platforms.prolific_replica.groups import (
    add_members,
    barred,
    code_actions,
    create_group,
    group_members,
    group_view,
    in_group,
    list_groups,
    membership_view,
    remove_members,
)
from server.app.platforms.prolific_replica.hooks import (
    EVENT_TYPES,
    Delivery,
    confirm_subscription,
    create_secret,
    create_subscription,
    delivered,
    deliveries,
    event_view,
    hook_secret,
    list_secrets,
    list_subscriptions,
    signed,
    status_event,
    study_payload,
    study_status_event,
    submission_payload,
    subscription_events,
    subscription_view,
)
from server.app.platforms.prolific_replica.messages import (
    MESSAGES_KEPT,
    RESEARCHER_ID,
    bulk_message,
    list_messages,
    message_view,
    send_message,
)
from server.app.platforms.prolific_replica.money import (
    HOURLY_REWARD,
    PUBLISHED,
    SERVICE_FEE,
    balance,
    pay_bonuses,
    reward_recommendations,
    set_up_bonuses,
    study_cost,
    with_fees,
)
from server.app.platforms.prolific_replica.studies import (
    CODE_ACTIONS,
    DEVICES,
    GROUP_FILTERS,
    LARGEST_MAXIMUM_MINUTES,
    PUBLISHED_CHANGES,
    STUDY_ACTIONS,
    create_study,
    publish_due,
    transition_study,
    update_study,
)
from server.app.platforms.prolific_replica.submissions import (
    COUNTED_STATUSES,
    DECIDED_FROM,
    MIN_REJECTION_MESSAGE,
    SUBMISSION_ACTIONS,
    bulk_approve,
    list_submissions,
    requests_return,
    return_reason,
    submission_counts,
    transition_submission,
)
from server.app.platforms.prolific_replica.views import (
    HOLDING,
    concurrency_limit,
    places_taken,
    study_view,
    submission_detail,
    submission_view,
    taking_part,
)

__all__ = [
    "CODE_ACTIONS",
    "COUNTED_STATUSES",
    "DECIDED_FROM",
    "DEVICES",
    "ENDPOINTS",
    "EVENT_TYPES",
    "GROUP_FILTERS",
    "HOLDING",
    "HOURLY_REWARD",
    "LARGEST_MAXIMUM_MINUTES",
    "MESSAGES_KEPT",
    "MIN_REJECTION_MESSAGE",
    "PLACEHOLDERS",
    "PROJECT_ID",
    "PUBLISHED",
    "PUBLISHED_CHANGES",
    "REPLICA_PATH",
    "RESEARCHER_ID",
    "ROUTES",
    "SERVICE_FEE",
    "STUDY_ACTIONS",
    "STUDY_CHANGES",
    "SUBMISSION_ACTIONS",
    "WORKSPACE_ID",
    "Call",
    "Delivery",
    "Refusal",
    "ReplicaTransport",
    "StudyChange",
    "Workspace",
    "add_members",
    "balance",
    "barred",
    "bulk_approve",
    "bulk_message",
    "code_actions",
    "completion_url",
    "concurrency_limit",
    "confirm_subscription",
    "create_group",
    "create_secret",
    "create_study",
    "create_subscription",
    "delivered",
    "deliveries",
    "error_body",
    "event_view",
    "group_members",
    "group_view",
    "handle",
    "hook_secret",
    "in_group",
    "is_replica_study",
    "list_groups",
    "list_messages",
    "list_secrets",
    "list_submissions",
    "list_subscriptions",
    "membership_view",
    "message_view",
    "new_id",
    "pay_bonuses",
    "places_taken",
    "publish_due",
    "remove_members",
    "requests_return",
    "return_reason",
    "reward_recommendations",
    "send_message",
    "set_up_bonuses",
    "signed",
    "status_event",
    "study_cost",
    "study_payload",
    "study_status_event",
    "study_view",
    "submission_counts",
    "submission_detail",
    "submission_payload",
    "submission_view",
    "subscription_events",
    "subscription_view",
    "taking_part",
    "transition_study",
    "transition_submission",
    "update_study",
    "with_fees",
    "workspace_of",
]
