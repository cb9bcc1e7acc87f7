"""Engine and session factory; SQLite gets WAL, foreign keys and a busy timeout."""

from __future__ import annotations

import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from types import ModuleType

import orjson
from sqlalchemy import Connection, Engine, create_engine, event, make_url
from sqlalchemy.orm import Session, sessionmaker

fcntl: ModuleType | None
try:
    import fcntl
except ImportError:  # not on Windows: processes then meet in SQLite's own busy handler
    fcntl = None


def _json_dumps(value) -> str:
    """JSON columns through orjson: a batch stores its tracker state and answer, and the
    standard library's encoder was ≈ 8 % of a batch's CPU. Non-string keys become strings
    and NumPy scalars plain numbers, as ``json.dumps`` would make them."""
    return orjson.dumps(value, option=orjson.OPT_NON_STR_KEYS | orjson.OPT_SERIALIZE_NUMPY).decode()


def make_engine(url: str) -> Engine:
    """An engine for ``url``; SQLite connections are configured for concurrent use."""
    json_codec = {"json_serializer": _json_dumps, "json_deserializer": orjson.loads}
    if url.startswith("sqlite"):
        engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": 30}, **json_codec)
        event.listen(engine, "connect", _sqlite_pragmas)
        return engine
    return create_engine(url, pool_pre_ping=True, pool_size=10, max_overflow=20, **json_codec)


def _sqlite_pragmas(dbapi_connection, _record) -> None:
    cursor = dbapi_connection.cursor()
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.execute("PRAGMA foreign_keys=ON")
    cursor.execute("PRAGMA synchronous=NORMAL")
    cursor.execute("PRAGMA busy_timeout=30000")
    cursor.close()


class SqliteWriteLock:
    """Lets one write transaction at a time into a SQLite database.

    SQLite has a single writer, and writers that collide on its lock wait in its busy
    handler, which sleeps 1, 2, 5, 10 … 100 ms between tries: under load the lock is
    often free while every writer sleeps. Here the threads of a process queue on a Python
    lock and the processes on an ``flock`` of ``<database>-writelock`` (beside SQLite's own
    ``-wal`` and ``-shm``), and both wake the next writer the moment the last one is done."""

    def __init__(self, path: str | None):
        self._threads = threading.Lock()
        usable = fcntl is not None and path and path != ":memory:" and not path.startswith("file:")
        self._path = f"{path}-writelock" if usable else None
        self._fd: int | None = None

    def __enter__(self) -> None:
        self._threads.acquire()
        try:
            if self._path is not None and fcntl is not None:
                if self._fd is None:  # opened on first use: read-only users never create the file
                    self._fd = os.open(self._path, os.O_RDWR | os.O_CREAT, 0o644)
                fcntl.flock(self._fd, fcntl.LOCK_EX)
        except BaseException:
            self._threads.release()
            raise

    def __exit__(self, *_exc) -> None:
        if self._fd is not None and fcntl is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
        self._threads.release()

    def close(self) -> None:
        with self._threads:
            if self._fd is not None:
                os.close(self._fd)
                self._fd = None


class Database:
    """Owns the engine; hands out transactional sessions."""

    def __init__(self, url: str):
        self.url = url
        self.engine = make_engine(url)
        self._sessions = sessionmaker(self.engine, expire_on_commit=False)
        #: an embedded database: every call is a local file access, never a network wait
        self.embedded = url.startswith("sqlite")
        self._write_lock = SqliteWriteLock(make_url(url).database) if self.embedded else nullcontext()

    @contextmanager
    def transaction(self, rollback_only: bool = False, write: bool = False) -> Iterator[Session]:
        """A session whose work commits on success (rolls back on error, or always if ``rollback_only``).

        ``write``: a transaction that reads, then writes what it read depends on (SQLite: it
        takes the write lock and begins IMMEDIATE, so no other writer can commit between
        its reads and its writes, which SQLite would answer with "database is locked")."""
        with self._write_lock if write else nullcontext(), self._sessions() as session:
            if write and self.embedded:
                session.connection().exec_driver_sql("BEGIN IMMEDIATE")
            try:
                yield session
            except BaseException:
                session.rollback()
                raise
            if rollback_only:
                session.rollback()
            else:
                session.commit()

    def read(self) -> Connection:
        """A Core connection for reads (``with db.read() as conn``); nothing it does is committed."""
        return self.engine.connect()

    @contextmanager
    def write(self) -> Iterator[Connection]:
        """A Core connection in a transaction that commits on success (``with db.write() as conn``);
        on SQLite, one such transaction at a time (``SqliteWriteLock``)."""
        with self._write_lock, self.engine.begin() as conn:
            yield conn

    def dispose(self) -> None:
        self.engine.dispose()
        if isinstance(self._write_lock, SqliteWriteLock):
            self._write_lock.close()
