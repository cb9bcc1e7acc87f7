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
