"""Engine and session factory; SQLite gets WAL, foreign keys and a busy timeout."""

from __future__ import annotations

import os
import select
import sqlite3
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from types import ModuleType

import orjson
from sqlalchemy import Connection, Engine, create_engine, event, make_url
from sqlalchemy.exc import InvalidatePoolError, OperationalError
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


#: seconds a SQLite connection waits for another writer's lock unless told otherwise (migrations,
#: training, the command line); the server's requests wait ``Settings.sqlite_busy_timeout_s``
BUSY_TIMEOUT_S = 30.0


def make_engine(url: str, busy_timeout_s: float = BUSY_TIMEOUT_S) -> Engine:
    """An engine for ``url``; SQLite connections are configured for concurrent use and wait
    ``busy_timeout_s`` for a lock another connection holds before "database is locked"."""
    json_codec = {"json_serializer": _json_dumps, "json_deserializer": orjson.loads}
    if url.startswith("sqlite"):
        engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": busy_timeout_s}, **json_codec)
        busy_ms = max(1, round(busy_timeout_s * 1000))

        def _pragmas(dbapi_connection, _record) -> None:
            _sqlite_pragmas(dbapi_connection, busy_ms)

        event.listen(engine, "connect", _pragmas)
        return engine
    # up to 30 connections a process, as before (10 kept + 20 overflow), now all kept once opened:
    # overflow connections were closed on their return, so that under load (closed loop, 64 clients)
    # connections were opened and closed all the time, ≈ 1,400 in a 30-second benchmark, each a
    # backend started and ended on the server and a log-in on both sides
    engine = create_engine(url, pool_size=30, max_overflow=0, **json_codec)
    event.listen(engine, "checkout", _ping_if_server_spoke(engine))
    return engine


def _ping_if_server_spoke(engine: Engine):
    """A pool ``checkout`` hook that does what ``pool_pre_ping`` did for a networked database
    without its round trip on every checkout (a ``SELECT 1``: ≈ 0.3 ms of a batch's CPU, two
    per batch). A pooled connection sits idle between transactions and its server has nothing
    to say to it; a server that shut down, restarted or terminated the backend sent its FATAL
    message and closed the socket. So the socket is asked (a zero-timeout ``poll``): only when it
    has something to read is the connection pinged as ``pool_pre_ping`` would, and when that
    fails the whole pool is invalidated as ``pool_pre_ping`` does (the request then gets a
    fresh connection, as before)."""

    def checkout(dbapi_connection, record, _proxy) -> None:
        try:
            fd = dbapi_connection.fileno()
        except Exception:  # noqa: BLE001  (no socket: closed or broken, let the ping decide)
            fd = -1
        if fd >= 0:
            poller = select.poll()
            poller.register(fd, select.POLLIN | select.POLLPRI)
            if not poller.poll(0):
                return  # quiet: as alive as a ping would have found it
        try:
            engine.dialect.do_ping(dbapi_connection)
        except Exception as exc:  # noqa: BLE001  (any failure: the connection is not usable)
            raise InvalidatePoolError(f"connection lost: {type(exc).__name__}") from exc

    return checkout


def _sqlite_pragmas(dbapi_connection, busy_ms: int) -> None:
    cursor = dbapi_connection.cursor()
    cursor.execute(f"PRAGMA busy_timeout={int(busy_ms)}")  # first: WAL mode itself may wait on a lock
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.execute("PRAGMA foreign_keys=ON")
    cursor.execute("PRAGMA synchronous=NORMAL")
    cursor.close()


def _locked(what: str) -> OperationalError:
    """The error SQLite itself gives a writer that waited too long (the server answers it 503)."""
    return OperationalError(what, None, sqlite3.OperationalError("database is locked"))


class SqliteWriteLock:
    """Lets one write transaction at a time into a SQLite database.

    SQLite has a single writer, and writers that collide on its lock wait in its busy
    handler, which sleeps 1, 2, 5, 10 … 100 ms between tries: under load the lock is
    often free while every writer sleeps. Here the threads of a process queue on a Python
    lock and the processes on an ``flock`` of ``<database>-writelock`` (beside SQLite's own
    ``-wal`` and ``-shm``), and both wake the next writer the moment the last one is done.

    ``timeout_s``: a writer that cannot have the lock within it gets SQLite's own "database is
    locked" ``OperationalError`` (the server answers 503 with ``Retry-After``) instead of waiting
    in line behind a writer that is itself stuck. Threads still wait on the Python lock (woken
    the moment it is free); the file lock is then tried without blocking, at most a few
    milliseconds apart. ``None``: wait as long as it takes."""

    def __init__(self, path: str | None, timeout_s: float | None = None):
        self.timeout_s = timeout_s
        self._threads = threading.Lock()
        usable = fcntl is not None and path and path != ":memory:" and not path.startswith("file:")
        self._path = f"{path}-writelock" if usable else None
        self._fd: int | None = None

    def __enter__(self) -> None:
        timeout = self.timeout_s
        deadline = None if timeout is None else time.monotonic() + timeout
        if not self._threads.acquire(timeout=-1 if timeout is None else timeout):
            raise _locked(f"another writer of this process held the write lock for {timeout:g} s")
        try:
            if self._path is not None and fcntl is not None:
                if self._fd is None:  # opened on first use: read-only users never create the file
                    self._fd = os.open(self._path, os.O_RDWR | os.O_CREAT, 0o644)
                if deadline is None:
                    fcntl.flock(self._fd, fcntl.LOCK_EX)
                else:
                    self._flock_until(self._fd, deadline)
        except BaseException:
            self._threads.release()
            raise

    def _flock_until(self, fd: int, deadline: float) -> None:
        assert fcntl is not None
        pause = 0.0002
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    raise _locked(f"another process held the write lock for {self.timeout_s:g} s") from None
                time.sleep(pause)
                pause = min(pause * 2, 0.002)

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

    def __init__(self, url: str, busy_timeout_s: float | None = None):
        """``busy_timeout_s`` (SQLite): how long a transaction waits for another writer, in
        ``SqliteWriteLock`` and then in SQLite's busy handler, before "database is locked" (the
        server's requests); ``None``: in line for the lock as long as it takes, then
        ``BUSY_TIMEOUT_S`` in SQLite's handler (migrations, training, the command line)."""
        self.url = url
        self.engine = make_engine(url, BUSY_TIMEOUT_S if busy_timeout_s is None else busy_timeout_s)
        self._sessions = sessionmaker(self.engine, expire_on_commit=False)
        #: an embedded database: every call is a local file access, never a network wait
        self.embedded = url.startswith("sqlite")
        #: reads outside a transaction on a networked database: no ``BEGIN`` and no ``ROLLBACK``
        #: round trip around them (PostgreSQL reads at READ COMMITTED take a snapshot per statement
        #: either way); SQLite's driver begins no transaction for reads already
        self._read_engine = self.engine if self.embedded else \
            self.engine.execution_options(isolation_level="AUTOCOMMIT")
        self._write_lock = (SqliteWriteLock(make_url(url).database, busy_timeout_s) if self.embedded
                            else nullcontext())

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
        """A Core connection for reads (``with db.read() as conn``); nothing it does is committed
        (on a networked database each statement commits on its own: use it for reads only)."""
        return self._read_engine.connect()

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
