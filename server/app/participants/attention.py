"""Instructional attention checks between agents (the study file's ``[attention_checks]``).

The participant is asked to move a robot to a star on a small open grid with the arrow keys.
The server decides from the moves it receives: the check is passed when the star is reached
within the moves allowed and failed when they run out; either way the participant goes on to
the next agent. Each move is one request of ``perform`` (its event, kind ``attention_move``,
holds the cell before and after), so a retried move counts once and a reload shows the check
as it is.
"""

from __future__ import annotations

from typing import Any

from sqlalchemy import Connection, func, select

from server.app.errors import ApiError
from server.app.participants import assignment, views
from server.app.participants.transaction import Transaction
from server.app.schemas import AttentionCheckView
from server.app.storage.records import Record, load
from server.app.storage.tables import CHECKS
from server.app.storage.vocabulary import CheckStatus
from server.domains.base import ACTIONS

# Row and column steps of each arrow, on a grid drawn with row 0 at the top.
STEPS = {"UP": (-1, 0), "DOWN": (1, 0), "LEFT": (0, -1), "RIGHT": (0, 1)}


def step(cell: int, size: int, action: str) -> int:
    """The cell after ``action``; a move into the edge stays where it is."""
    row, column = divmod(cell, size)
    d_row, d_column = STEPS[action]
    row = min(max(row + d_row, 0), size - 1)
    column = min(max(column + d_column, 0), size - 1)
    return row * size + column


def active_check(c: Connection, participant_id: int) -> Record | None:
    """The participant's check being taken, if any."""
    return load(
        c, CHECKS, CHECKS.c.participant_id == participant_id, CHECKS.c.status == CheckStatus.ACTIVE
    )


def view(c: Connection, check: Any) -> AttentionCheckView:
    total = c.scalar(
        select(func.count())
        .select_from(CHECKS)
        .where(CHECKS.c.participant_id == check.participant_id)
    )
    return views.check_view(check, int(total or 0))


def move(transaction: Transaction, action: str) -> Record:
    """One arrow in the check being taken; at the star (passed) or at the last move allowed
    (failed) the check ends and the next agent begins. Returns the check."""
    check = active_check(transaction.c, transaction.participant.id)
    if check is None:
        raise ApiError(409, "there is no attention check in progress")
    transaction.track(check)
    cell = int(check.cell)
    next_cell = step(cell, check.size, action)
    check.cell = next_cell
    check.moves = [*check.moves, action]
    transaction.event.update(state=cell, action=ACTIONS.index(action), next_state=next_cell)
    if next_cell == check.star_cell:
        check.status = CheckStatus.PASSED
    elif len(check.moves) >= check.moves_allowed:
        check.status = CheckStatus.FAILED
    if check.status != CheckStatus.ACTIVE:
        check.finished_at = transaction.now
        transaction.flush()
        assignment.continue_after(transaction, check.after_ordinal)
    return check
