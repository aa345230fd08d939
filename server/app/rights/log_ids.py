"""Participants' platform ids kept out of the server's log. Every line ``bam-study serve``
writes through Python's logging (its own, uvicorn's access log with ``--access-log``, httpx's
line per call to Prolific) has each platform id replaced by its pseudonym, as the export writes
it: a study link's worker and assignment parameters (MTurk's ``workerId`` and
``assignmentId``, Prolific's ``PROLIFIC_PID`` and ``SESSION_ID``: every platform's ``ids``)
and a Prolific submission id in a URL path (``/submissions/<id>/``: Prolific's submission id is
the participant's ``SESSION_ID``). A line can then be matched with the export's rows, and
neither an erasure nor a scrub has to reach the log files. A study's or HIT's id is not a
person's and stays.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterable
from typing import Any

from server.app.platform_registry import platforms
from server.app.rights.pseudonyms import ASSIGNMENT, WORKER, pseudonym

# Loggers whose lines carry URLs: uvicorn's access log, httpx's line per request sent.
LOGGERS = ("uvicorn.access", "httpx")
_PREFIX = {"platform_participant_id": WORKER, "platform_submission_id": ASSIGNMENT}
# A Prolific id: 24 hexadecimal digits (the platform's ID_PATTERN).
_SUBMISSION = re.compile(r"(/submissions/)([0-9a-fA-F]{24})(?=[/?\s\"']|$)")


def _parameters() -> dict[str, str]:
    """Each platform's id parameter whose value is a person's, with its pseudonym's prefix."""
    return {
        parameter: _PREFIX[field]
        for platform in platforms()
        for field, parameter in platform.ids.items()
        if field in _PREFIX
    }


class PseudonymousIds(logging.Filter):
    """Replaces the platform ids in each record's message by their pseudonyms (module
    docstring); the record is always kept."""

    def __init__(self, secret: str) -> None:
        super().__init__()
        self.secret = secret
        prefixes = _parameters()
        self.prefixes = prefixes
        names = "|".join(re.escape(name) for name in sorted(prefixes))
        self.query = re.compile(rf"([?&]({names})=)([^&#\s\"']+)")

    def redact(self, text: str) -> str:
        """``text`` with every platform id in it replaced by its pseudonym."""
        text = self.query.sub(
            lambda m: m[1] + str(pseudonym(self.secret, m[3], self.prefixes[m[2]])), text
        )
        return _SUBMISSION.sub(lambda m: m[1] + str(pseudonym(self.secret, m[2], ASSIGNMENT)), text)

    def filter(self, record: logging.LogRecord) -> bool:
        # The arguments replaced one by one, not merged into the message: uvicorn's access
        # formatter reads them (the path, the status code) by position.
        if isinstance(record.msg, str):
            record.msg = self.redact(record.msg)
        if isinstance(record.args, tuple):
            record.args = tuple(self._argument(value) for value in record.args)
        elif isinstance(record.args, dict):
            record.args = {key: self._argument(value) for key, value in record.args.items()}
        return True

    def _argument(self, value: Any) -> Any:
        if value is None or isinstance(value, int | float):
            return value
        text = str(value)  # httpx logs its URL objects
        redacted = self.redact(text)
        return value if redacted == text else redacted


def keep_ids_out_of_logs(secret: str, loggers: Iterable[str] = LOGGERS) -> PseudonymousIds:
    """Install ``PseudonymousIds`` on ``loggers`` (a logger's filter sees the records logged
    through it, not those its children pass up, so each is named); returns the filter."""
    ids = PseudonymousIds(secret)
    for name in loggers:
        logger = logging.getLogger(name)
        for old in [f for f in logger.filters if isinstance(f, PseudonymousIds)]:
            logger.removeFilter(old)
        logger.addFilter(ids)
    return ids
