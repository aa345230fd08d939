"""Checking and typing the cells of an exported table: every problem an ``InputError`` that
names the file, the row and the column."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pandas as pd

from analysis.options import InputError

TRUE_WORDS = {"true", "t", "yes", "y", "1"}


FALSE_WORDS = {"false", "f", "no", "n", "0"}


def require_columns(frame: pd.DataFrame, columns: tuple[str, ...], source: str) -> None:
    missing = [column for column in columns if column not in frame.columns]
    if missing:
        found = ", ".join(repr(str(c)) for c in frame.columns) or "none"
        raise InputError(
            f"{source}: missing column(s) {', '.join(repr(c) for c in missing)} (found: {found})"
        )


def where(source: str, row: int) -> str:
    """Row ``row`` (0-based, in the table's order) as a reader finds it: rows count from 1,
    and in a CSV file the header is line 1."""
    if source.endswith(".csv"):
        return f"{source}, row {row + 1} (line {row + 2})"
    return f"{source}, row {row + 1}"


def fail(source: str, row: int, column: str, message: str, count: int = 1) -> None:
    more = f" (and {count - 1} more such row{'s' if count > 2 else ''})" if count > 1 else ""
    raise InputError(f"{where(source, row)}, column {column!r}: {message}{more}")


def raw(frame: pd.DataFrame, column: str) -> tuple[pd.Series, pd.Series]:
    """The column as stripped strings, and where it is missing (empty, NaN or None)."""
    values = frame[column]
    missing = values.isna()
    text = values.astype(object).where(~missing, "").map(str).str.strip()
    return text, missing | (text == "")


def first_bad(
    frame: pd.DataFrame, column: str, source: str, bad: pd.Series, describe: Callable[[str], str]
) -> None:
    if bad.any():
        row = int(np.flatnonzero(bad.to_numpy())[0])
        text, _ = raw(frame, column)
        fail(source, row, column, describe(text.iloc[row]), int(bad.sum()))


def _check_missing(frame: pd.DataFrame, column: str, source: str) -> pd.Series:
    text, missing = raw(frame, column)
    first_bad(frame, column, source, missing, lambda _: "missing value")
    return text


def text(frame: pd.DataFrame, column: str, source: str) -> pd.Series:
    return _check_missing(frame, column, source)


def optional_text(values: pd.Series) -> pd.Series:
    return values.astype(object).where(values.notna(), "").map(str).str.strip()


def number(frame: pd.DataFrame, column: str, source: str) -> pd.Series:
    text = _check_missing(frame, column, source)
    numbers = pd.to_numeric(text, errors="coerce").astype(float)
    bad = ~np.isfinite(numbers)
    first_bad(frame, column, source, bad, lambda value: f"{value!r} is not a number")
    return numbers


def integer(frame: pd.DataFrame, column: str, source: str) -> pd.Series:
    numbers = number(frame, column, source)
    fractional = numbers != np.round(numbers)
    first_bad(frame, column, source, fractional, lambda value: f"{value} is not a whole number")
    negative = numbers < 0
    first_bad(frame, column, source, negative, lambda value: f"{value} is negative")
    return numbers.astype(np.int64)


def boolean(frame: pd.DataFrame, column: str, source: str) -> pd.Series:
    text = _check_missing(frame, column, source).str.lower()
    bad = ~text.isin(TRUE_WORDS | FALSE_WORDS)
    first_bad(frame, column, source, bad, lambda value: f"{value!r} is not true or false")
    return text.isin(TRUE_WORDS)
