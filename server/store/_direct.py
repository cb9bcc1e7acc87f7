"""Core statements run straight on the driver's cursor, for the tracking batch's hot path.

A Core ``Connection.execute`` costs 25–50 µs of Python per statement (execution context,
parameter and result processing, result object) and a batch runs four of them: measured
in-process, that overhead was a fifth of a batch's CPU. A ``DirectStatement`` is compiled
once per dialect *by SQLAlchemy* (its SQL, its parameter style and PostgreSQL casts, the
column types' own bind and result processors, found once), then executed on the DBAPI
cursor of the same connection, inside whatever transaction that connection is in — so
what is stored and read back is exactly what Core would store and read.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, cast

from sqlalchemy import Connection
from sqlalchemy.engine import Dialect
from sqlalchemy.sql import ClauseElement
from sqlalchemy.sql.compiler import SQLCompiler

_Processor = Callable[[Any], Any]


@dataclass(frozen=True)
class _Compiled:
    sql: str
    #: parameter names in positional order (qmark/format styles), None for named styles
    order: tuple[str, ...] | None
    #: values the statement itself carries (``status == "open"``)
    fixed: Mapping[str, Any]
    #: (parameter, bind processor) for the parameters whose type converts them
    binds: tuple[tuple[str, _Processor], ...]
    #: per selected column, its result processor (None: the driver's value as is)
    results: tuple[_Processor | None, ...]


class DirectStatement:
    """One Core statement, compiled per dialect and executed on the raw DBAPI cursor."""

    def __init__(self, statement: ClauseElement):
        self.statement = statement
        self._compiled_for: dict[Dialect, _Compiled] = {}

    def _compiled(self, dialect: Dialect) -> _Compiled:
        compiled = self._compiled_for.get(dialect)
        if compiled is None:
            c = cast(SQLCompiler, self.statement.compile(dialect=dialect))
            names = {b: c.bind_names[b] for b in c.binds.values()}
            binds = []
            for b, name in names.items():
                proc = b.type.dialect_impl(dialect).bind_processor(dialect)
                if proc is not None and (name, proc) not in binds:
                    binds.append((name, proc))
            columns = getattr(self.statement, "selected_columns", ())
            compiled = _Compiled(
                sql=c.string,
                order=None if c.positiontup is None else tuple(c.positiontup),
                fixed={name: b.value for b, name in names.items() if not b.required},
                binds=tuple(binds),
                results=tuple(col.type.dialect_impl(dialect).result_processor(dialect, None) for col in columns),
            )
            self._compiled_for[dialect] = compiled
        return compiled

    @staticmethod
    def _args(c: _Compiled, params: Mapping[str, Any]) -> Any:
        values = {**c.fixed, **params}
        for name, proc in c.binds:
            values[name] = proc(values[name])
        return values if c.order is None else [values[name] for name in c.order]

    def execute(self, conn: Connection, params: Mapping[str, Any]) -> int:
        """Run it once; the number of rows it changed (an UPDATE's, an INSERT's)."""
        c = self._compiled(conn.dialect)
        cursor = conn.connection.driver_connection.cursor()  # type: ignore[union-attr]
        try:
            cursor.execute(c.sql, self._args(c, params))
            return int(cursor.rowcount)
        finally:
            cursor.close()

    def execute_many(self, conn: Connection, rows: Sequence[Mapping[str, Any]]) -> None:
        c = self._compiled(conn.dialect)
        cursor = conn.connection.driver_connection.cursor()  # type: ignore[union-attr]
        try:
            cursor.executemany(c.sql, [self._args(c, row) for row in rows])
        finally:
            cursor.close()

    def first(self, conn: Connection, params: Mapping[str, Any]) -> tuple[Any, ...] | None:
        """The first row of a SELECT, its values through the columns' result processors."""
        c = self._compiled(conn.dialect)
        cursor = conn.connection.driver_connection.cursor()  # type: ignore[union-attr]
        try:
            cursor.execute(c.sql, self._args(c, params))
            row = cursor.fetchone()
        finally:
            cursor.close()
        if row is None:
            return None
        return tuple(v if proc is None or v is None else proc(v) for v, proc in zip(row, c.results, strict=True))
