"""The device check before consent (the study file's ``[device_check]``): the page asks for one
arrow key press and measures the window and the browser; the server judges the report against
the study's needs. A participant whose device cannot take part is turned away (status
``incompatible``, its reasons in the status change's note) and leaves with the platform's code
for that, if it has one (Prolific's INCOMPATIBLE_DEVICE); one whose device passes stays at the
consent page, and the passed check is the request's event.
"""

from __future__ import annotations

import re

from server.app.errors import ApiError
from server.app.participants.statuses import set_status
from server.app.participants.transaction import Transaction
from server.app.schemas import DeviceCheckRequest
from server.app.storage.vocabulary import ParticipantStatus
from server.app.study_file import DeviceCheck

FEATURE_NAMES = {"fetch": "fetch", "dialog": "dialogs", "svg": "SVG drawing"}
# A browser's name and major version in its User-Agent, most specific first (Edge and Opera
# also say Chrome; Chrome also says Safari).
BROWSERS = (
    ("Edge", re.compile(r"Edg/(\d+)")),
    ("Opera", re.compile(r"OPR/(\d+)")),
    ("Firefox", re.compile(r"Firefox/(\d+)")),
    ("Chrome", re.compile(r"Chrom(?:e|ium)/(\d+)")),
    ("Safari", re.compile(r"Version/(\d+)[\d.]* .*Safari/")),
)


def problems(needs: DeviceCheck, report: DeviceCheckRequest) -> list[str]:
    """Why the device cannot take part, one clause each (none: it can)."""
    found = []
    if not report.arrow_key:
        found.append("no arrow key was pressed")
    if report.width < needs.min_width or report.height < needs.min_height:
        found.append(
            f"the window is {report.width}x{report.height}, smaller than the "
            f"{needs.min_width}x{needs.min_height} the study needs"
        )
    if report.missing:
        lacking = ", ".join(FEATURE_NAMES[name] for name in report.missing)
        found.append(f"the browser lacks {lacking}")
    return found


def browser_name(user_agent: str | None) -> str:
    """The browser's name and major version ("Chrome 120"), or "another browser"; nothing more
    of the User-Agent is kept."""
    for name, pattern in BROWSERS:
        match = pattern.search(user_agent or "")
        if match:
            return f"{name} {match.group(1)}"
    return "another browser"


def check_device(transaction: Transaction, report: DeviceCheckRequest, browser: str) -> None:
    """Judge the page's report: a device that cannot take part turns the participant away."""
    participant = transaction.participant
    if participant.status != ParticipantStatus.ARRIVED:
        raise ApiError(409, f"the device is checked before consent (status {participant.status})")
    needs = transaction.study.device_check
    if not needs.enabled:
        raise ApiError(409, "this study has no device check")
    found = problems(needs, report)
    if found:
        note = f"{'; '.join(found)} ({browser})"
        set_status(
            transaction.c, participant, ParticipantStatus.INCOMPATIBLE, transaction.now, note
        )
