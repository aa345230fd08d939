"""Rows for the request path: read with one Core statement, changed by attribute, written back
with one UPDATE of the changed columns.

Every participant request runs a handful of statements. Through the ORM's unit of work, or with
Core statements built anew for each request, building the statements costs several times their
execution, so the request path (``flow.perform`` and its handlers) uses these prepared ones: one
SELECT by id and one INSERT per table, and one UPDATE per table and set of changed columns,
built once and cached.
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import cache
from typing import Any

from sqlalchemy import Connection, Insert, Select, Table, bindparam, insert, select, update
from sqlalchemy.sql import ColumnElement
from sqlalchemy.sql.dml import Update


def table_of(model: Any) -> Table:
    """The Core table of an ORM model."""
    table = model.__table__
    assert isinstance(table, Table)
    return table


@cache
def _select_by_id(table: Table) -> Select[Any]:
    return select(table).where(table.c.id == bindparam("row_id"))


@cache
def _update(table: Table, columns: frozenset[str]) -> Update:
    return (
        update(table)
        .where(table.c.id == bindparam("row_id"))
        .values({name: bindparam(f"new_{name}") for name in sorted(columns)})
    )


@cache
def _insert(table: Table) -> Insert:
    return insert(table)


class Record:
    """One row: attribute access, and the columns changed since it was read.

    Only the changed columns are written back: other writers may change other columns of the
    same row meanwhile (the update manager a session's update counters, an experimenter a
    participant's exclusion), and on PostgreSQL their transactions can interleave with ours.
    """

    __slots__ = ("_changed", "_table", "_values")

    def __init__(self, table: Table, values: Mapping[Any, Any]) -> None:
        object.__setattr__(self, "_table", table)
        object.__setattr__(self, "_values", dict(values))
        object.__setattr__(self, "_changed", set())

    def __getattr__(self, name: str) -> Any:
        try:
            return self._values[name]
        except KeyError:
            raise AttributeError(f"{self._table.name} has no column {name!r}") from None

    def __setattr__(self, name: str, value: Any) -> None:
        if name not in self._values:
            raise AttributeError(f"{self._table.name} has no column {name!r}")
        self._values[name] = value
        self._changed.add(name)

    def save(self, connection: Connection) -> None:
        """Write the changed columns back (a prepared UPDATE per set of columns)."""
        if not self._changed:
            return
        changed = frozenset(self._changed)
        parameters = {f"new_{name}": self._values[name] for name in changed}
        connection.execute(
            _update(self._table, changed), {"row_id": self._values["id"], **parameters}
        )
        self._changed.clear()


def get(connection: Connection, table: Table, row_id: int) -> Record | None:
    """The row with this id (prepared statement)."""
    row = connection.execute(_select_by_id(table), {"row_id": row_id}).mappings().first()
    return None if row is None else Record(table, row)


def load(connection: Connection, table: Table, *where: ColumnElement[bool]) -> Record | None:
    """The first row matching ``where`` (a statement built for the call: not for hot paths)."""
    row = connection.execute(select(table).where(*where)).mappings().first()
    return None if row is None else Record(table, row)


def load_all(
    connection: Connection, table: Table, *where: ColumnElement[bool], order_by: Any = None
) -> list[Record]:
    query = select(table).where(*where)
    if order_by is not None:
        query = query.order_by(order_by)
    return [Record(table, row) for row in connection.execute(query).mappings()]


def add(connection: Connection, table: Table, **values: Any) -> int:
    """INSERT a row (prepared statement); returns its id."""
    result = connection.execute(_insert(table), values)
    key = result.inserted_primary_key
    assert key is not None
    return int(key[0])
