"""What a statement's result says beyond its rows."""

from __future__ import annotations

from typing import Any, cast

from sqlalchemy import CursorResult, Result


def changed(result: Result[Any]) -> int:
    """How many rows an UPDATE or DELETE changed. ``Session.execute`` is typed as returning a
    plain ``Result``; for these statements it is a ``CursorResult``, which counts them."""
    return cast(CursorResult[Any], result).rowcount


def tuples(result: Result[Any]) -> list[tuple[Any, ...]]:
    """The rows as plain tuples, for unpacking into domain types (SQLAlchemy 2.1 types the
    items of a row of a long ``select`` as ``object``, and deprecates ``Result.tuples``)."""
    return [tuple(row) for row in result]


def first(result: Result[Any]) -> tuple[Any, ...] | None:
    row = result.first()
    return None if row is None else tuple(row)
