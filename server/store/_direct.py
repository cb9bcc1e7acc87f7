"""Core statements run straight on the driver's cursor, for the tracking batch's hot path.

A Core ``Connection.execute`` costs 25–50 µs of Python per statement (execution context,
parameter and result processing, result object) and a batch runs four of them: measured
in-process, that overhead was a fifth of a batch's CPU. A ``DirectStatement`` is compiled
once per dialect *by SQLAlchemy* (its SQL, its parameter style and PostgreSQL casts, the
column types' own bind and result processors, found once), then executed on the DBAPI
cursor of the same connection, inside whatever transaction that connection is in — so
what is stored and read back is exactly what Core would store and read, and a driver error
is raised as Core would raise it (the server's 503 for a locked database depends on that).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, cast
from weakref import WeakKeyDictionary

from sqlalchemy import Connection
from sqlalchemy.engine import Dialect
from sqlalchemy.exc import DBAPIError
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
        #: per engine's dialect, for as long as the engine lives (tests make many)
        self._compiled_for: WeakKeyDictionary[Dialect, _Compiled] = WeakKeyDictionary()

    def _compiled(self, dialect: Dialect) -> _Compiled:
        compiled = self._compiled_for.get(dialect)
        if compiled is None:
            c = cast(SQLCompiler, self.statement.compile(dialect=dialect))
            names = {b: c.bind_names[b] for b in c.binds.values()}
            binds: dict[str, _Processor] = {}  # one processor per parameter name, however often it appears
            for b, name in names.items():
                proc = b.type.dialect_impl(dialect).bind_processor(dialect)
                if proc is not None:
                    binds.setdefault(name, proc)
            columns = getattr(self.statement, "selected_columns", ())
            compiled = _Compiled(
                sql=c.string,
                order=None if c.positiontup is None else tuple(c.positiontup),
                fixed={name: b.value for b, name in names.items() if not b.required},
                binds=tuple(binds.items()),
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

    @staticmethod
    def _run(conn: Connection, c: _Compiled, args: Any, action: Callable[[Any], Any]) -> Any:
        """``action(cursor)`` on a cursor of ``conn``'s driver connection. A driver error is raised
        as SQLAlchemy raises it (``OperationalError`` for a locked or unreachable database, which
        the server answers 503, ``IntegrityError``, …), and a connection the error shows lost is
        invalidated, as Core does for its own statements."""
        dialect = conn.dialect
        driver = conn.connection.driver_connection
        dbapi_error = dialect.loaded_dbapi.Error
        try:
            cursor = driver.cursor()  # type: ignore[union-attr]
            try:
                return action(cursor)
            finally:
                cursor.close()
        except dbapi_error as exc:
            lost = dialect.is_disconnect(exc, driver, None)
            if lost:
                conn.invalidate(exc)
            raise DBAPIError.instance(c.sql, args, exc, dbapi_error,
                                      connection_invalidated=lost, dialect=dialect) from exc

    def execute(self, conn: Connection, params: Mapping[str, Any]) -> int:
        """Run it once; the number of rows it changed (an UPDATE's, an INSERT's)."""
        c = self._compiled(conn.dialect)
        args = self._args(c, params)

        def run(cursor: Any) -> int:
            cursor.execute(c.sql, args)
            return int(cursor.rowcount)

        return self._run(conn, c, args, run)

    def execute_many(self, conn: Connection, rows: Sequence[Mapping[str, Any]]) -> None:
        c = self._compiled(conn.dialect)
        args = [self._args(c, row) for row in rows]
        self._run(conn, c, args, lambda cursor: cursor.executemany(c.sql, args))

    def first(self, conn: Connection, params: Mapping[str, Any]) -> tuple[Any, ...] | None:
        """The first row of a SELECT, its values through the columns' result processors."""
        c = self._compiled(conn.dialect)
        args = self._args(c, params)

        def run(cursor: Any) -> Any:
            cursor.execute(c.sql, args)
            return cursor.fetchone()

        row = self._run(conn, c, args, run)
        if row is None:
            return None
        return tuple(v if proc is None or v is None else proc(v) for v, proc in zip(row, c.results, strict=True))
