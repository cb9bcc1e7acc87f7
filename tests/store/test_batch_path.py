"""The per-batch database path's connection handling: reads without a transaction's round trips,
and connections the server dropped found before use (what ``pool_pre_ping`` did, without its
``SELECT 1`` on every checkout). The PostgreSQL tests skip on SQLite."""

from __future__ import annotations

import time
from datetime import UTC, datetime

import pytest
from sqlalchemy import text

from server.domain import BatchAnswer
from server.estimation.types import Estimate
from server.store import sessions

START = Estimate(None, 1.0, 2.0, 0, ((1.0, 0.0), (0.0, 1.0)), "init")


@pytest.fixture
def session_id(db, site_id) -> str:
    with db.transaction() as s:
        return sessions.add_session(s, "s-1", site_id, "owner-hash", "ekf", None, {"v": 0}, [START]).id


@pytest.fixture
def postgres(db):
    if db.embedded:
        pytest.skip("PostgreSQL only (LOCALIZER_TEST_DATABASE_URL)")
    return db


def _backend_pids(db) -> set[int]:
    """The server process ids of the connections resting in ``db``'s pool."""
    pids: set[int] = set()
    held = [db.engine.raw_connection() for _ in range(db.engine.pool.checkedin())]
    for conn in held:
        pids.add(conn.driver_connection.info.backend_pid)  # type: ignore[union-attr]
    for conn in held:
        conn.close()
    return pids


def test_a_read_leaves_no_transaction_open_on_postgres(postgres, session_id):
    with postgres.read() as conn:
        assert sessions.feed_state(conn, session_id) is not None
        info = conn.connection.driver_connection.info  # type: ignore[union-attr]
        assert info.transaction_status.name == "IDLE"  # no BEGIN was sent, none to roll back
    with postgres.write() as conn:  # writes still run in one transaction
        conn.execute(text("SELECT 1"))
        assert conn.connection.driver_connection.info.transaction_status.name == "INTRANS"  # type: ignore[union-attr]


def test_a_batch_is_read_and_written_on_connections_the_server_dropped(postgres, session_id):
    """A database restart (or an administrator) ends the pooled connections' backends; the next
    read and write get working connections, not a failed request."""
    for _ in range(2):  # two connections in the pool
        with postgres.read() as a, postgres.read() as b:
            a.execute(text("SELECT 1"))
            b.execute(text("SELECT 1"))
    pids = _backend_pids(postgres)
    assert pids
    other = type(postgres)(postgres.url)
    try:
        with other.write() as conn:
            for pid in pids:
                conn.execute(text("SELECT pg_terminate_backend(:p)"), {"p": pid})
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:  # the backends are gone (termination is asynchronous)
            with other.read() as conn:
                alive = conn.execute(text("SELECT count(*) FROM pg_stat_activity WHERE pid = ANY(:p)"),
                                     {"p": list(pids)}).scalar()
            if not alive:
                break
            time.sleep(0.01)
    finally:
        other.dispose()
    with postgres.read() as conn:
        state = sessions.feed_state(conn, session_id)
    assert state is not None and state.last_seq == -1
    answer = BatchAnswer(0, START, 0, 0, (), ())
    with postgres.write() as conn:
        assert sessions.save_batch(conn, session_id, expected_last_seq=-1, state={"v": 1}, answer=answer,
                                   first_idx=1, estimates=[])
    with postgres.read() as conn:
        assert sessions.batch_answer(conn, session_id, 0) == answer
    assert not pids & _backend_pids(postgres)


def test_a_read_on_sqlite_is_as_before(db, session_id):
    """SQLite's reads were never in a transaction of their own (its driver begins none for a SELECT)."""
    if not db.embedded:
        pytest.skip("SQLite only")
    with db.read() as conn:
        assert sessions.feed_state(conn, session_id) is not None
        assert not conn.connection.driver_connection.in_transaction  # type: ignore[union-attr]


STEP = Estimate(0.5, 1.5, 2.0, 0, ((1.2, 0.1), (0.1, 1.3)), "step")
START_TIME = datetime(2026, 12, 2, tzinfo=UTC)


def _stored_batches(db, session_id: str) -> list[tuple]:
    """The stored batch rows as the driver returns them (no column type processing)."""
    with db.read() as conn:
        return [tuple(r) for r in conn.exec_driver_sql(
            f"SELECT seq, answer, created_at, inputs FROM session_batches WHERE session_id = '{session_id}' "
            "ORDER BY seq")]


def test_the_batch_path_stores_what_core_stores(db, session_id):
    """``save_batch`` runs on the driver's cursor (``store._direct``): its rows must be the ones
    Core's own insert of the same values stores, byte for byte where the driver gives text."""
    from sqlalchemy import insert

    from server.tables import SessionBatch, TrackEstimate, utcnow

    answer = BatchAnswer(0, STEP, 1, 0, (), ())
    inputs = {"steps": [{"t": 1.5, "length_m": 0.7}], "scans": [], "fixes": [{"none": "nothing heard"}]}
    with db.write() as conn:
        assert sessions.save_batch(conn, session_id, expected_last_seq=-1, state={"v": 1}, answer=answer,
                                   first_idx=1, estimates=[STEP], inputs=inputs)
        conn.execute(insert(SessionBatch), [{"session_id": session_id, "seq": 1, "answer": answer.to_dict(),
                                             "created_at": utcnow(), "inputs": inputs}])
        conn.execute(insert(TrackEstimate), sessions._estimate_rows(session_id, 2, 1, [STEP]))
    direct, core = _stored_batches(db, session_id)
    assert direct[1] == core[1]  # the answer's JSON, as stored
    assert direct[3] == core[3] and direct[3] is not None  # the kept inputs' JSON
    assert type(direct[2]) is type(core[2])
    if isinstance(core[2], str):  # SQLite: the same text format, a moment apart
        assert len(direct[2]) == len(core[2]) and direct[2][:10] == core[2][:10]
    with db.read() as conn:
        rows = [tuple(r) for r in conn.exec_driver_sql(
            f"SELECT t, x, y, floor, building, covariance, source, seq FROM track_estimates "
            f"WHERE session_id = '{session_id}' AND idx > 0 ORDER BY idx")]
        state = sessions.feed_state(conn, session_id)
        assert sessions.batch_answer(conn, session_id, 0) == answer
    assert rows[0][:7] == rows[1][:7] and (rows[0][7], rows[1][7]) == (0, 1)
    assert state is not None and state.state == {"v": 1} and (state.last_seq, state.track_length) == (0, 2)


def test_the_batch_path_joins_its_connections_transaction(db, session_id):
    """A batch whose transaction fails after ``save_batch`` leaves nothing behind."""
    answer = BatchAnswer(0, STEP, 1, 0, (), ())
    with pytest.raises(RuntimeError), db.write() as conn:
        assert sessions.save_batch(conn, session_id, expected_last_seq=-1, state={"v": 1}, answer=answer,
                                   first_idx=1, estimates=[STEP])
        raise RuntimeError("after the write")
    with db.read() as conn:
        state = sessions.feed_state(conn, session_id)
        assert sessions.batch_answer(conn, session_id, 0) is None
    assert state is not None and (state.last_seq, state.track_length, state.state) == (-1, 1, {"v": 0})
    assert _stored_batches(db, session_id) == []
    with db.write() as conn:  # and a stale compare-and-set writes nothing
        assert not sessions.save_batch(conn, session_id, expected_last_seq=5, state={"v": 2}, answer=answer,
                                       first_idx=1, estimates=[STEP])
    assert _stored_batches(db, session_id) == []


def test_a_driver_error_is_raised_as_sqlalchemy_raises_it(db, session_id):
    """The server maps SQLAlchemy's errors (a locked database: 503); the batch path's statements
    run on the driver's cursor but raise the same classes."""
    from sqlalchemy.exc import IntegrityError

    answer = BatchAnswer(0, STEP, 1, 0, (), ())
    with db.write() as conn:
        assert sessions.save_batch(conn, session_id, expected_last_seq=-1, state={"v": 1}, answer=answer,
                                   first_idx=1, estimates=[STEP])
    with pytest.raises(IntegrityError), db.write() as conn:  # the same seq stored twice
        sessions._INSERT_ANSWER.execute(conn, {"session_id": session_id, "seq": 0, "answer": {},
                                               "created_at": START_TIME, "inputs": None})


def test_a_locked_sqlite_database_is_an_operational_error(db, session_id):
    """Another program holding SQLite's write lock: the compare-and-set UPDATE waits its busy
    timeout and fails with SQLAlchemy's ``OperationalError`` (answered 503), writing nothing."""
    import sqlite3

    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import OperationalError

    from server.db import Database

    if not db.embedded:
        pytest.skip("SQLite only")
    path = make_url(db.url).database
    impatient = Database(db.url, busy_timeout_s=0.05)
    blocker = sqlite3.connect(path, isolation_level=None)
    try:
        blocker.execute("BEGIN IMMEDIATE")
        answer = BatchAnswer(0, STEP, 1, 0, (), ())
        with pytest.raises(OperationalError, match="locked"), impatient.write() as conn:
            sessions.save_batch(conn, session_id, expected_last_seq=-1, state={"v": 1}, answer=answer,
                                first_idx=1, estimates=[STEP])
    finally:
        blocker.execute("ROLLBACK")
        blocker.close()
        impatient.dispose()
    assert _stored_batches(db, session_id) == []
