"""SQLite's write lock: one write transaction at a time, across processes too."""

from __future__ import annotations

import threading
import time

from server.db import Database, SqliteWriteLock


def _entry_order(hold, then) -> list[str]:
    """Enter ``hold()`` while a thread tries to enter ``then()``: the order in which the
    first is left and the second entered."""
    events: list[str] = []

    def other() -> None:
        with then():
            events.append("second in")

    with hold():
        thread = threading.Thread(target=other)
        thread.start()
        time.sleep(0.2)
        events.append("first out")
    thread.join(5)
    return events


def test_a_second_holder_waits_until_the_first_is_done(tmp_path):
    # Two locks on one database are two open files, as in two server processes:
    # only the flock keeps them apart (each has its own thread lock).
    path = str(tmp_path / "x.db")
    first, second = SqliteWriteLock(path), SqliteWriteLock(path)
    assert _entry_order(lambda: first, lambda: second) == ["first out", "second in"]
    assert (tmp_path / "x.db-writelock").exists()


def test_database_writes_take_the_lock(tmp_path):
    """Two Database objects on one file, as two server processes: the second write
    transaction starts only when the first has committed."""
    url = f"sqlite:///{tmp_path / 'z.db'}"
    first, second = Database(url), Database(url)
    try:
        assert _entry_order(first.write, second.write) == ["first out", "second in"]
    finally:
        first.dispose()
        second.dispose()


def test_threads_of_one_process_take_turns(tmp_path):
    lock = SqliteWriteLock(str(tmp_path / "y.db"))
    inside, most = [0], [0]

    def writer() -> None:
        for _ in range(30):
            with lock:
                inside[0] += 1
                most[0] = max(most[0], inside[0])
                time.sleep(0.001)  # give the other threads every chance to come in
                inside[0] -= 1

    threads = [threading.Thread(target=writer) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert most[0] == 1


def test_a_writer_with_a_timeout_gives_up_with_database_is_locked(tmp_path):
    """Another process (another lock on the file) or another thread of this one holding the
    write lock: a writer with ``timeout_s`` gets SQLite's own "database is locked" error
    within it (the server answers it 503), and the lock is usable once it is free."""
    import pytest
    from sqlalchemy.exc import OperationalError

    path = str(tmp_path / "t.db")
    holder, waiter = SqliteWriteLock(path), SqliteWriteLock(path, timeout_s=0.3)
    with holder:
        started = time.monotonic()
        with pytest.raises(OperationalError, match="database is locked"):
            waiter.__enter__()
        assert 0.25 < time.monotonic() - started < 2
    with waiter:  # free again: taken at once
        pass

    same = SqliteWriteLock(path, timeout_s=0.3)
    errors: list[Exception] = []

    def second() -> None:
        try:
            with same:
                pass
        except OperationalError as exc:
            errors.append(exc)

    with same:
        thread = threading.Thread(target=second)
        thread.start()
        thread.join(5)
    assert len(errors) == 1 and "database is locked" in str(errors[0])


def test_a_request_write_on_a_locked_database_is_503_well_before_the_busy_timeout(tmp_path):
    """An outside connection (a backup, an operator's sqlite3 shell) holds SQLite's write lock:
    a request that writes answers 503 with Retry-After after ``sqlite_busy_timeout_s``, not
    after the 30 s that migrations and training wait; nothing is stored; writes work again once
    the lock is released."""
    import sqlite3

    from fastapi.testclient import TestClient

    from server import migrate
    from server.app import create_app
    from server.db import BUSY_TIMEOUT_S
    from tests.conftest import ADMIN_KEY, make_settings

    path = tmp_path / "locked.db"
    url = f"sqlite:///{path}"
    migrate.upgrade(url)
    app = create_app(make_settings(url, sqlite_busy_timeout_s=0.5, embedded_worker=False))
    outside = sqlite3.connect(path, isolation_level=None)
    headers = {"Authorization": f"Bearer {ADMIN_KEY}"}
    try:
        with TestClient(app) as client:
            outside.execute("BEGIN IMMEDIATE")
            started = time.monotonic()
            answer = client.post("/api/v1/sites", json={"name": "blocked"}, headers=headers)
            waited = time.monotonic() - started
            assert answer.status_code == 503, answer.text
            assert int(answer.headers["Retry-After"]) > 0
            assert 0.4 < waited < BUSY_TIMEOUT_S / 3
            outside.execute("ROLLBACK")
            assert client.post("/api/v1/sites", json={"name": "blocked"}, headers=headers).status_code == 201
            assert [s["name"] for s in client.get("/api/v1/sites", headers=headers).json()] == ["blocked"]
    finally:
        outside.close()
