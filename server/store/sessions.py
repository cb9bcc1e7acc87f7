"""Tracking sessions, their stored batch answers and their tracks; crowd fingerprints a batch adds.

The per-batch path (``feed_state``, ``batch_answer``, ``save_batch`` and the crowd
statements) takes a Core ``Connection`` and runs statements built once at import: a batch
is the service's hottest request, and the ORM's per-statement work was most of its cost.
"""

from __future__ import annotations

from collections.abc import Sequence
from datetime import UTC, datetime
from typing import Any, cast

from sqlalchemy import Connection, Table, and_, bindparam, func, insert, select, update
from sqlalchemy.orm import Session

from server.domain import GATE_NOTES, BatchAnswer, FeedState, GateMarks, SessionInfo
from server.estimation.types import CrowdPoint, Estimate, FullState
from server.store._direct import DirectStatement
from server.store._results import tuples
from server.tables import Fingerprint, SessionBatch, Site, TrackEstimate, TrackingSession, utcnow

_SESSIONS, _SITES = cast(Table, TrackingSession.__table__), cast(Table, Site.__table__)
_BATCHES, _ESTIMATES = cast(Table, SessionBatch.__table__), cast(Table, TrackEstimate.__table__)
_FINGERPRINTS = cast(Table, Fingerprint.__table__)

#: the batch path's statements (``feed_state``, ``save_batch``) run on the driver's cursor (``_direct``); its
#: inserts name every column, so a batch's ``created_at`` is given (by the column default's own ``utcnow``)
_FEED_STATE = DirectStatement(
    select(
        _SESSIONS.c.site_id, _SESSIONS.c.owner_key, _SESSIONS.c.model_id, _SESSIONS.c.status, _SESSIONS.c.state,
        _SESSIONS.c.last_seq, _SESSIONS.c.track_length, _SITES.c.revision.label("site_revision"),
    )
    .join(_SITES, _SITES.c.id == _SESSIONS.c.site_id)
    .where(_SESSIONS.c.id == bindparam("session_id"))
)
_STORED_ANSWER = select(_BATCHES.c.answer).where(
    _BATCHES.c.session_id == bindparam("session_id"), _BATCHES.c.seq == bindparam("seq")
)
_CLAIM_SEQ = DirectStatement(
    update(_SESSIONS)
    .where(
        _SESSIONS.c.id == bindparam("sid"),
        _SESSIONS.c.last_seq == bindparam("expected_seq"),
        _SESSIONS.c.status == "open",
    )
    .values(state=bindparam("new_state"), last_seq=bindparam("new_seq"), track_length=bindparam("new_length"))
)


def _insert_every_column(table: Table) -> DirectStatement:
    """An INSERT naming each column as a parameter of its own name (no column default applies)."""
    return DirectStatement(insert(table).values({c.name: bindparam(c.name) for c in table.columns}))


_INSERT_ANSWER = _insert_every_column(_BATCHES)
_INSERT_ESTIMATES = _insert_every_column(_ESTIMATES)
_DATE_INITIAL = (
    update(_ESTIMATES)
    .where(_ESTIMATES.c.session_id == bindparam("sid"), _ESTIMATES.c.idx == 0, _ESTIMATES.c.t.is_(None))
    .values(t=bindparam("init_t"))
)
_NEARBY_CROWD = (
    select(_FINGERPRINTS.c.id, _FINGERPRINTS.c.x, _FINGERPRINTS.c.y, _FINGERPRINTS.c.floor, _FINGERPRINTS.c.rss,
           _FINGERPRINTS.c.samples)
    .where(
        _FINGERPRINTS.c.site_id == bindparam("site_id"),
        _FINGERPRINTS.c.source == "crowd",
        _FINGERPRINTS.c.building == bindparam("building"),
        _FINGERPRINTS.c.floor == bindparam("floor"),
        _FINGERPRINTS.c.x.between(bindparam("x0"), bindparam("x1")),
        _FINGERPRINTS.c.y.between(bindparam("y0"), bindparam("y1")),
    )
    .order_by(_FINGERPRINTS.c.id)
    .with_for_update()
)
_INSERT_CROWD = insert(_FINGERPRINTS)
_UPDATE_CROWD = (
    update(_FINGERPRINTS)
    .where(_FINGERPRINTS.c.id == bindparam("fid"))
    .values(x=bindparam("new_x"), y=bindparam("new_y"), rss=bindparam("new_rss"), samples=bindparam("new_samples"))
)


def _info(row: TrackingSession) -> SessionInfo:
    stored = (row.state or {}).get("estimate")
    return SessionInfo(
        id=row.id, site_id=row.site_id, owner_key=row.owner_key, filter=row.filter, model_id=row.model_id,
        status=row.status, estimate=None if stored is None else Estimate.from_dict(stored),
        created_at=row.created_at, last_seq=row.last_seq, track_length=row.track_length,
        filter_params=dict((row.state or {}).get("tracker_params") or {}) or None,
    )


def _estimate_rows(session_id: str, first_idx: int, seq: int | None, estimates: Sequence[Estimate],
                   states: Sequence[FullState | None] = ()) -> list[dict]:
    """Rows of ``estimates``, each with its tracker's whole state from ``states`` (one per estimate, None:
    NULL; no ``states``: NULL for all)."""
    full = states or [None] * len(estimates)
    return [
        {"session_id": session_id, "idx": first_idx + i, "seq": seq, "t": e.t, "x": e.x, "y": e.y, "floor": e.floor,
         "building": e.building, "covariance": [list(e.covariance[0]), list(e.covariance[1])], "source": e.source,
         "state": None if f is None else f.to_dict()}
        for i, (e, f) in enumerate(zip(estimates, full, strict=True))
    ]


#: a stored estimate's columns, in the order ``_estimate`` takes them
_ESTIMATE_COLUMNS = (_ESTIMATES.c.t, _ESTIMATES.c.x, _ESTIMATES.c.y, _ESTIMATES.c.floor, _ESTIMATES.c.covariance,
                     _ESTIMATES.c.source, _ESTIMATES.c.building)


def _estimate(t: float | None, x: float, y: float, floor: int, c: list[list[float]], source: str,
              building: int) -> Estimate:
    """A stored estimate (``_ESTIMATE_COLUMNS``) as the domain type: the inverse of ``_estimate_rows``."""
    return Estimate(t, x, y, floor, ((c[0][0], c[0][1]), (c[1][0], c[1][1])), source, building)


# --- open, read, close ------------------------------------------------------------------------


def add_session(
    s: Session, session_id: str, site_id: int, owner_key: str, filter: str, model_id: int | None,
    state: dict, estimates: Sequence[Estimate], states: Sequence[FullState | None] = (),
    opening_state: dict | None = None,
) -> SessionInfo:
    """A new open session; ``estimates`` (the initial position, if given) start its track;
    ``opening_state``: ``state`` kept as it opened, for a replay (None: not kept)."""
    row = TrackingSession(
        id=session_id, site_id=site_id, owner_key=owner_key, filter=filter, model_id=model_id,
        status="open", state=state, last_seq=-1, track_length=len(estimates), opening_state=opening_state,
    )
    s.add(row)
    s.flush()
    if estimates:
        _INSERT_ESTIMATES.execute_many(s.connection(), _estimate_rows(session_id, 0, None, estimates, states))
    return _info(row)


#: a session's last batch seq and track length (in lists and site polls), from the primary-key indexes of
#: its batches and estimates (``save_batch`` writes them in the same transaction as the session's ``last_seq``
#: and ``track_length``): SQLite stores those two columns after the tracker ``state``, so reading them
#: walks the state's overflow pages (≈ 20 KB a PF session, 18 ms of a 1,000-session list's SQL)
_LAST_IDX = _ESTIMATES.alias("last_estimate")
_LAST_ESTIMATE_IDX = select(func.max(_LAST_IDX.c.idx)).where(_LAST_IDX.c.session_id == _SESSIONS.c.id).scalar_subquery()
_LAST_SEQ = func.coalesce(
    select(func.max(_BATCHES.c.seq)).where(_BATCHES.c.session_id == _SESSIONS.c.id).scalar_subquery(), -1)
_LIST_COLUMNS = (
    _SESSIONS.c.id, _SESSIONS.c.site_id, _SESSIONS.c.owner_key, _SESSIONS.c.filter, _SESSIONS.c.model_id,
    _SESSIONS.c.status, _SESSIONS.c.created_at, _LAST_SEQ, func.coalesce(_ESTIMATES.c.idx + 1, 0),
    *_ESTIMATE_COLUMNS,
)


def list_sessions(
    s: Session, owner_key: str | None, site_id: int | None, status: str | None, limit: int
) -> list[SessionInfo]:
    """Newest first; ``owner_key`` None lists every owner's.

    Each session's ``estimate`` is its track's last estimate (one primary-key lookup per listed
    row in the same query): the session's row is read only up to its tracker state, which holds
    the same estimate but also the whole filter (a PF's particles); ``last_seq`` and
    ``track_length`` come from indexes (``_LAST_SEQ``)."""
    query = (
        select(*_LIST_COLUMNS)
        .select_from(_SESSIONS.outerjoin(_ESTIMATES, and_(
            _ESTIMATES.c.session_id == _SESSIONS.c.id, _ESTIMATES.c.idx == _LAST_ESTIMATE_IDX)))
        .order_by(_SESSIONS.c.created_at.desc(), _SESSIONS.c.id.desc())  # ix_tracking_sessions_created_id, read backwards
        .limit(limit)
    )
    if owner_key is not None:
        query = query.where(_SESSIONS.c.owner_key == owner_key)
    if site_id is not None:
        query = query.where(_SESSIONS.c.site_id == site_id)
    if status is not None:
        query = query.where(_SESSIONS.c.status == status)
    return [
        SessionInfo(
            id=sid, site_id=site, owner_key=owner, filter=filter, model_id=model_id, status=st,
            estimate=None if x is None else _estimate(t, x, y, floor, c, source, building),
            created_at=created_at, last_seq=last_seq, track_length=track_length,
        )
        for sid, site, owner, filter, model_id, st, created_at, last_seq, track_length, t, x, y, floor, c, source, building
        in cast(Sequence[tuple[Any, ...]], s.execute(query).all())  # at once: a tenth cheaper than row by row
    ]


def get_session(s: Session, session_id: str) -> SessionInfo | None:
    row = s.scalar(
        select(TrackingSession).where(TrackingSession.id == session_id).execution_options(populate_existing=True)
    )
    return None if row is None else _info(row)


def track(s: Session, session_id: str) -> list[Estimate]:
    rows = s.execute(
        select(*_ESTIMATE_COLUMNS).where(_ESTIMATES.c.session_id == session_id).order_by(_ESTIMATES.c.idx)
    )
    return [_estimate(*row) for row in tuples(rows)]


def track_with_states(s: Session, session_id: str) -> tuple[list[Estimate], list[FullState | None]]:
    """The track (as ``track``) and, per estimate, the tracker's whole state stored with it (None: a
    tracker without one, or an estimate stored before states were), in one read: what the smoother needs."""
    rows = tuples(s.execute(
        select(*_ESTIMATE_COLUMNS, _ESTIMATES.c.state).where(_ESTIMATES.c.session_id == session_id)
        .order_by(_ESTIMATES.c.idx)
    ))
    return [_estimate(*row[:-1]) for row in rows], [None if row[-1] is None else FullState.from_dict(row[-1])
                                                     for row in rows]


def replay_inputs(s: Session, session_id: str) -> tuple[dict | None, list[dict | None]]:
    """The session's opening state and its batches' inputs in seq order (None where not kept)."""
    opening = s.execute(select(_SESSIONS.c.opening_state).where(_SESSIONS.c.id == session_id)).scalar()
    inputs: Sequence[dict | None] = s.execute(select(_BATCHES.c.inputs).where(_BATCHES.c.session_id == session_id)
                       .order_by(_BATCHES.c.seq)).scalars().all()
    return opening, list(inputs)


def estimates_after(s: Session, session_id: str, after_idx: int, limit: int) -> list[tuple[int, Estimate]]:
    """(idx, estimate) of the session's track after index ``after_idx``, at most ``limit``, in order:
    what a live stream has not sent yet (any process may have written them)."""
    rows = s.execute(
        select(_ESTIMATES.c.idx, *_ESTIMATE_COLUMNS)
        .where(_ESTIMATES.c.session_id == session_id, _ESTIMATES.c.idx > after_idx)
        .order_by(_ESTIMATES.c.idx)
        .limit(limit)
    )
    return [(row[0], _estimate(*row[1:])) for row in tuples(rows)]


def batch_seq_range(s: Session, session_id: str, first_idx: int, last_idx: int) -> tuple[int, int] | None:
    """(lowest, highest) batch seq of the track's estimates first_idx..last_idx (None: none came from a batch)."""
    row = s.execute(
        select(func.min(_ESTIMATES.c.seq), func.max(_ESTIMATES.c.seq))
        .where(_ESTIMATES.c.session_id == session_id, _ESTIMATES.c.idx.between(first_idx, last_idx))
    ).one()
    lo, hi = cast(tuple[int | None, int | None], tuple(row))
    return None if lo is None or hi is None else (lo, hi)


def gate_marks(s: Session, session_id: str, seqs: tuple[int, int] | None = None) -> dict[int, GateMarks]:
    """Track index → what the innovation gate refused there (``GateMarks``), for the scan
    estimates whose fingerprint fix or landmark snap it refused, from the stored batch answers
    (``rejected_fixes`` and ``rejected_snaps`` name scan indexes of a batch) and the estimates'
    batch seq; no column of its own.

    A batch's scans are applied in time order and each applied scan leaves one ``scan``
    estimate; a note names which applied scan it was (``applied``), so the batch's scan
    estimate of that rank is its, whatever order the phone listed the scans in. Answers stored
    before notes kept ``applied``: the batch's applied scans are its scan indexes minus
    ``skipped_scans``, and the k-th of them by index is taken as the k-th applied (exact when
    the batch listed its scans in time order, as a phone sends them).

    ``seqs`` (first, last): only the batches of that seq range (a page of the track reads
    the answers of its own batches, not every batch's)."""
    refusing: dict[int, dict] = {}
    batches = select(_BATCHES.c.seq, _BATCHES.c.answer).where(_BATCHES.c.session_id == session_id)
    if seqs is not None:
        batches = batches.where(_BATCHES.c.seq.between(seqs[0], seqs[1]))
    for seq, answer in tuples(s.execute(batches)):
        if answer and any(answer.get(key) for key in GATE_NOTES):
            refusing[seq] = answer
    if not refusing:
        return {}
    rows = tuples(s.execute(
        select(_ESTIMATES.c.idx, _ESTIMATES.c.seq)
        .where(_ESTIMATES.c.session_id == session_id, _ESTIMATES.c.seq.in_(list(refusing)),
               _ESTIMATES.c.source == "scan")
        .order_by(_ESTIMATES.c.idx)
    ))
    scan_rows: dict[int, list[int]] = {}
    for idx, seq in rows:
        scan_rows.setdefault(seq, []).append(idx)
    out: dict[int, GateMarks] = {}
    for seq, answer in refusing.items():
        skipped = {n["index"] for n in answer.get("skipped_scans", [])}
        total = int(answer.get("applied_scans", 0)) + len(skipped)
        applied = [i for i in range(total) if i not in skipped]
        position = {scan: k for k, scan in enumerate(applied)}
        idxs = scan_rows.get(seq, [])
        for key, mark in GATE_NOTES.items():
            for note in answer.get(key, []):
                k = note.get("applied", position.get(note["index"]))
                if k is not None and k < len(idxs):
                    out[idxs[k]] = out.get(idxs[k], GateMarks()) | mark
    return out


def open_sessions_of_site(s: Session, site_id: int) -> dict[str, int]:
    """session id → track length of every open session on the site (the length from the estimates'
    index, as a list reads it: 1,000 open PF sessions poll in 2 ms of SQL instead of 8)."""
    rows = s.execute(
        select(_SESSIONS.c.id, func.coalesce(_LAST_ESTIMATE_IDX, -1) + 1)
        .where(_SESSIONS.c.site_id == site_id, _SESSIONS.c.status == "open")
    )
    return dict(tuples(rows))


def close_session(s: Session, session_id: str) -> bool:
    """Close an open session; False when it was already closed."""
    result = s.connection().execute(
        update(TrackingSession)
        .where(TrackingSession.id == session_id, TrackingSession.status == "open")
        .values(status="closed", closed_at=datetime.now(UTC))
    )
    return result.rowcount == 1


# --- the per-batch path ---------------------------------------------------------------------


def feed_state(conn: Connection, session_id: str) -> FeedState | None:
    """The session's row with its site's revision, or None. A plain read (no lock):
    ``save_batch`` checks that nothing changed since."""
    row = _FEED_STATE.first(conn, {"session_id": session_id})
    return None if row is None else FeedState(*row)


def batch_answer(conn: Connection, session_id: str, seq: int) -> BatchAnswer | None:
    stored = conn.execute(_STORED_ANSWER, {"session_id": session_id, "seq": seq}).scalar()
    return None if stored is None else BatchAnswer.from_dict(stored)


def save_batch(
    conn: Connection,
    session_id: str,
    *,
    expected_last_seq: int,
    state: dict,
    answer: BatchAnswer,
    first_idx: int,
    estimates: Sequence[Estimate],
    init_t: float | None = None,
    states: Sequence[FullState | None] = (),
    inputs: dict | None = None,
) -> bool:
    """Compare-and-set: store the batch's outcome only if the session is still open at ``expected_last_seq``.

    The UPDATE comes first, so it takes the row lock (PostgreSQL) or the write lock
    (SQLite) before anything else is written; a concurrent feeder of the same session
    finds ``last_seq`` moved and gets ``False`` (nothing written; it re-reads and retries).
    ``inputs``: the batch as the tracker saw it, kept for a replay (None: not kept).
    """
    claimed = _CLAIM_SEQ.execute(conn, {
        "sid": session_id, "expected_seq": expected_last_seq, "new_state": state, "new_seq": answer.seq,
        "new_length": first_idx + len(estimates),
    })
    if claimed != 1:
        return False
    _INSERT_ANSWER.execute(
        conn, {"session_id": session_id, "seq": answer.seq, "answer": answer.to_dict(), "created_at": utcnow(),
               "inputs": inputs})
    if estimates:
        _INSERT_ESTIMATES.execute_many(conn, _estimate_rows(session_id, first_idx, answer.seq, estimates, states))
    if init_t is not None:  # the initial estimate takes the time of the session's first input
        conn.execute(_DATE_INITIAL, {"sid": session_id, "init_t": init_t})
    return True


# --- crowd fingerprints (written in the batch's transaction) -------------------------------


def nearby_crowd_points(
    conn: Connection, site_id: int, floor: int, x: float, y: float, radius_m: float, building: int = 0,
) -> list[tuple[int, CrowdPoint]]:
    """(id, point) of the crowd fingerprints of a floor of a building in the box of ±radius around (x, y),
    locked for the merge. A stored point keeps its merged count, not per-transmitter counts."""
    rows = conn.execute(_NEARBY_CROWD, {
        "site_id": site_id, "building": building, "floor": floor, "x0": x - radius_m, "x1": x + radius_m,
        "y0": y - radius_m, "y1": y + radius_m,
    })
    return [(fid, CrowdPoint(px, py, pfloor, rss, samples, building=building))
            for fid, px, py, pfloor, rss, samples in tuples(rows)]


def add_crowd_fingerprint(
    conn: Connection, site_id: int, point: CrowdPoint, heading_deg: float | None, t: float | None
) -> None:
    conn.execute(_INSERT_CROWD, [{
        "site_id": site_id, "source": "crowd", "building": point.building, "floor": point.floor, "x": point.x,
        "y": point.y,
        "heading_deg": None if heading_deg is None else heading_deg % 360.0, "t": t, "device": None,
        "rss": point.rss, "samples": point.count,
    }])


def update_crowd_fingerprint(conn: Connection, fingerprint_id: int, point: CrowdPoint) -> None:
    conn.execute(_UPDATE_CROWD, {
        "fid": fingerprint_id, "new_x": point.x, "new_y": point.y, "new_rss": point.rss, "new_samples": point.count,
    })
