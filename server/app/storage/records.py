"""Rows for the request path: read with one statement, changed by attribute, written back
with one UPDATE of the changed columns.

Every participant request runs a handful of statements. Through the ORM's unit of work, or with
Core statements built anew for each request, building the statements costs several times their
execution, so the request path (``flow.perform`` and its handlers) uses these prepared ones: one
SELECT by id and one INSERT per table, and one UPDATE per table and set of changed columns,
built once and cached.

They run on the driver's cursor inside the SQLAlchemy transaction (``Native``): each is compiled
once per dialect, with SQLAlchemy's own bind and result processors and Python-side column
defaults, so they read and write exactly what ``Connection.execute`` would, and the driver's
errors come out as SQLAlchemy's (an ``IntegrityError`` stays one). Executing a statement through
``Connection.execute`` builds an execution context, a result and its metadata each time: on a
participant's move that was a third of the server's CPU time, against a tenth through the
cursor.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import cache
from typing import Any, cast

from sqlalchemy import Connection, Insert, Select, Table, bindparam, insert, select, update
from sqlalchemy.engine import Dialect
from sqlalchemy.exc import DBAPIError, InvalidRequestError
from sqlalchemy.sql import ColumnElement
from sqlalchemy.sql.compiler import SQLCompiler
from sqlalchemy.sql.dml import Update
from sqlalchemy.sql.elements import ClauseElement
from sqlalchemy.types import TypeEngine

Processor = Callable[[Any], Any] | None
REQUIRED = object()  # a bind parameter with no value of its own


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
        .values(
            {name: bindparam(f"new_{name}", type_=table.c[name].type) for name in sorted(columns)}
        )
    )


@cache
def _insert(table: Table, columns: frozenset[str]) -> Insert:
    statement = insert(table).values(
        {name: bindparam(name, type_=table.c[name].type) for name in sorted(columns)}
    )
    return statement.returning(table.c.id)


@dataclass
class Native:
    """A statement compiled for one dialect, run on the driver's cursor (module docstring)."""

    sql: str
    names: tuple[str, ...] | None  # the binds in order (positional paramstyles), or None
    binds: tuple[tuple[str, Processor, Any], ...]  # name, processor, the value if not given
    columns: tuple[tuple[str, TypeEngine[Any]], ...]  # the result's keys and types
    dialect: Dialect
    # The result's processors: some depend on the type the driver says it returns (a float
    # column on PostgreSQL), so they are made at the first result.
    processors: tuple[Processor, ...] | None = None

    @classmethod
    @cache
    def of(cls, statement: ClauseElement, dialect: Dialect) -> Native:
        compiled = cast(SQLCompiler, statement.compile(dialect=dialect))
        if any(bind.expanding for bind in compiled.binds.values()):
            # Their SQL is rendered anew for each list of values.
            raise ValueError(f"a prepared statement cannot hold an expanding IN: {statement}")
        binds = tuple(
            (
                name,
                bind.type.dialect_impl(dialect).bind_processor(dialect),
                REQUIRED if bind.required else bind.effective_value,
            )
            for name, bind in compiled.binds.items()
        )
        columns = tuple(
            (column.key, column.type.dialect_impl(dialect))
            for column in getattr(statement, "exported_columns", ())
        )
        names = tuple(compiled.positiontup or ()) if compiled.positional else None
        return cls(compiled.string, names, binds, columns, dialect)

    def parameters(self, values: Mapping[str, Any]) -> Any:
        processed = {}
        for name, process, literal in self.binds:
            value = values[name] if name in values else literal
            if value is REQUIRED:
                raise InvalidRequestError(f"a value is required for bind parameter {name!r}")
            processed[name] = value if process is None else process(value)
        if self.names is None:
            return processed
        return tuple(processed[name] for name in self.names)

    def run(self, connection: Connection, values: Mapping[str, Any]) -> Any:
        """Execute; the cursor, positioned on the result (the caller closes it)."""
        parameters = self.parameters(values)
        cursor = connection.connection.dbapi_connection.cursor()  # type: ignore[union-attr]
        try:
            cursor.execute(self.sql, parameters)
        except self.dialect.loaded_dbapi.Error as error:
            cursor.close()
            raise DBAPIError.instance(
                self.sql, parameters, error, self.dialect.loaded_dbapi.Error, dialect=self.dialect
            ) from error
        return cursor

    def first(self, connection: Connection, values: Mapping[str, Any]) -> dict[str, Any] | None:
        """The first row as a dict of column keys, or None."""
        cursor = self.run(connection, values)
        try:
            row = cursor.fetchone()
            if self.processors is None:
                self.processors = tuple(
                    kind.result_processor(self.dialect, described[1])
                    for (_, kind), described in zip(self.columns, cursor.description, strict=True)
                )
        finally:
            cursor.close()
        if row is None:
            return None
        return {
            key: value if process is None else process(value)
            for (key, _), process, value in zip(self.columns, self.processors, row, strict=True)
        }

    def execute(self, connection: Connection, values: Mapping[str, Any]) -> None:
        self.run(connection, values).close()


def fetch_one(
    connection: Connection, statement: ClauseElement, values: Mapping[str, Any]
) -> dict[str, Any] | None:
    """The first row of a prepared SELECT (a dict of its column keys), or None."""
    return Native.of(statement, connection.dialect).first(connection, values)


def _with_defaults(table: Table, values: Mapping[str, Any]) -> dict[str, Any]:
    """``values`` and the table's Python-side column defaults for the columns not given."""
    row = dict(values)
    for column in table.columns:
        default = column.default
        if column.key in row or default is None:
            continue
        if default.is_callable:
            row[column.key] = default.arg(None)  # type: ignore[attr-defined]
        elif default.is_scalar:
            row[column.key] = default.arg  # type: ignore[attr-defined]
    return row


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
        statement = Native.of(_update(self._table, changed), connection.dialect)
        statement.execute(connection, {"row_id": self._values["id"], **parameters})
        self._changed.clear()


def get(connection: Connection, table: Table, row_id: int) -> Record | None:
    """The row with this id (prepared statement)."""
    row = fetch_one(connection, _select_by_id(table), {"row_id": row_id})
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
    """INSERT a row (prepared statement, the table's Python-side defaults filled in); returns
    its id."""
    row = _with_defaults(table, values)
    inserted = Native.of(_insert(table, frozenset(row)), connection.dialect).first(connection, row)
    assert inserted is not None
    return int(inserted["id"])
