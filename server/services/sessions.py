"""Tracking sessions: open, feed batches, read, close. Free of HTTP.

The tracking itself is ``SessionEstimator.apply_batch`` (``server.estimation.session``);
this service reads, computes, writes and retries. Every batch is applied exactly once:
the session row is read without a lock, the batch is computed, and the outcome (tracker
state, the stored answer, the new track estimates, crowd fingerprints) is written in one
transaction that starts with a compare-and-set on ``last_seq``; if another request
applied a batch meanwhile the write is abandoned and the request starts over (and finds
its seq already answered, when it was a duplicate). See ``store.sessions.save_batch``.

A batch costs two round trips to the database: one read (the session row with its
site's revision; the site's transmitters, settings, walls and serving model come from
the per-process ``SiteContexts`` while that revision holds) and one write transaction.
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal, TypeVar

from sqlalchemy import Connection
from sqlalchemy.orm import Session

from server.auth import Principal
from server.db import Database
from server.domain import MAX_BATCH_SCANS, MAX_BATCH_STEPS, BatchAnswer, FeedState, GateMarks, SessionInfo, floor_names
from server.errors import Conflict, Invalid, NotFound, ServiceError, TooLarge
from server.estimation.replay import RecordedBatch, RecordingFixes, replays, smoothed_by_replay
from server.estimation.session import SessionEstimator
from server.estimation.tracking import find_merge_target, merge_points
from server.estimation.tracking.smoother import smooth_track
from server.estimation.tracking.tuning import BadParam, check_params
from server.estimation.types import (
    Area,
    CrowdCandidate,
    Estimate,
    Fix,
    InitialHeading,
    LateInputs,
    NoFix,
    Scan,
    SiteMap,
    Step,
    TrackerFailure,
)
from server.services.lru import Lru
from server.services.positioning import Positioning, ServingModel
from server.services.site_context import SiteContexts
from server.store import models as model_store
from server.store import sessions as store
from server.store import sites as site_store

log = logging.getLogger(__name__)

#: how often a feed starts over after losing the compare-and-set to a concurrent request
MAX_ATTEMPTS = 20
#: crowd fingerprints closer than this (same floor) are merged
CROWD_MERGE_RADIUS_M = 1.0
#: ``smoother=particles`` replays at most this many batches (≈ 1.5 ms each: 15 s of one request's CPU)
MAX_REPLAY_BATCHES = 10_000
#: particle-smoothed tracks kept per process, by (session, last applied seq, site revision): a track read
#: again costs its reads, not its replay
PARTICLE_TRACKS_CACHED = 32

_Row = TypeVar("_Row", SessionInfo, FeedState)
#: how a track is smoothed (``SessionService.track``)
Smoother = Literal["rts", "particles"]


@dataclass(frozen=True)
class InitialPosition:
    """Where a phone says a session starts; ``covariance`` in m² (None: the default); ``heading``
    the walker's direction there when the phone knows it independently of its compass (None: not
    known so)."""

    x: float
    y: float
    floor: int
    covariance: tuple[tuple[float, float], tuple[float, float]] | None = None
    building: int = 0
    heading: InitialHeading | None = None


@dataclass(frozen=True)
class ModelFixes:
    """The positioning service as the tracker's ``FixSource``: a scan's fix from the session's
    model (or the site's serving one); a scan it cannot place gives ``NoFix``."""

    positioning: Positioning | None
    site_id: int
    model_id: int | None
    serving: ServingModel | None

    def fix(self, scan: Scan, near: Area | None) -> Fix:
        if self.positioning is None:
            raise NoFix("no fingerprint model service is configured")
        try:
            return self.positioning.locate(
                self.site_id, scan.rss, heading_deg=scan.heading_deg, model_id=self.model_id,
                near=None if near is None else (near.x, near.y), radius_m=None if near is None else near.radius_m,
                serving=self.serving if self.model_id is None else None,
            ).fix
        except ServiceError as exc:
            raise NoFix(_reason(exc)) from None


class SessionService:
    """``positioning`` is the fingerprint-model service (``locate``); without one, scans give no fix."""

    def __init__(self, db: Database, positioning: Positioning | None = None):
        self.db = db
        self.positioning = positioning
        self.sites = SiteContexts(db)
        self._particle_tracks: Lru[tuple[str, int, str], list[Estimate]] = Lru(PARTICLE_TRACKS_CACHED)

    # -- open / read / close ---------------------------------------------------------------
    def open(
        self, principal: Principal, site_id: int, filter: str, model_id: int | None = None,
        initial: InitialPosition | None = None, seed: int | None = None,
        filter_params: Mapping[str, float] | None = None,
    ) -> SessionInfo:
        """A new session; ``seed`` fixes its tracker's random draws (default: from the session id),
        ``filter_params`` override its tracker's defaults (``tracking.tuning``)."""
        try:
            params = check_params(filter, dict(filter_params or {}))
        except BadParam as exc:
            raise Invalid([{"field": "filter_params" if exc.name is None else f"filter_params.{exc.name}",
                            "msg": str(exc)}]) from None
        session_id = str(uuid.uuid4())
        est = SessionEstimator(filter, seed=uuid.UUID(session_id).int % 2**32 if seed is None else seed,
                               tracker_params=params)
        with self.db.transaction() as s:
            if site_store.site_settings(s, site_id) is None:
                raise NotFound(f"site {site_id} does not exist")
            if model_id is not None and model_store.model_site(s, model_id) != site_id:
                raise Invalid([{"field": "model_id", "msg": f"model {model_id} is not a model of site {site_id}"}])
            estimates: list[Estimate] = []
            if initial is not None:
                floors = site_store.floor_ids(s, site_id)
                if floors and (initial.building, initial.floor) not in floors:
                    where = "" if initial.building == 0 else f" of building {initial.building}"
                    raise Invalid([{"field": "initial.floor",
                                    "msg": f"floor {initial.floor}{where} is not a floor of this site "
                                           f"{floor_names(floors)}"}])
                walls = site_store.floor_walls(s, site_id, initial.floor, initial.building)
                estimates.append(est.start([initial.x, initial.y], initial.covariance, initial.floor, walls, None, "init",
                                           initial.building, heading=initial.heading))
            state = est.to_dict()
            return store.add_session(s, session_id, site_id, principal.key_hash, filter, model_id, state, estimates,
                                     [est.full_state] if estimates else [], opening_state=state if replays(filter) else None)

    def list_sessions(self, principal: Principal, site_id: int | None, status: str | None, limit: int) -> list[SessionInfo]:
        """The caller's sessions (every session for an admin key), newest first."""
        owner = None if principal.scope == "admin" else principal.key_hash
        with self.db.transaction() as s:
            return store.list_sessions(s, owner, site_id, status, limit)

    def get(self, principal: Principal, session_id: str) -> SessionInfo:
        with self.db.transaction() as s:
            return _visible(store.get_session(s, session_id), principal, session_id)

    def track(self, principal: Principal, session_id: str, smoothed: bool = False,
              smoother: Smoother = "rts") -> list[Estimate]:
        """The stored track, oldest first; ``smoothed``: the same estimates (times, floors, buildings,
        sources) smoothed, kept in the floors' walkable areas — by the fixed-interval RTS over the
        stored estimates (``server.estimation.tracking.smoother``), or with ``smoother`` "particles" a
        particle-filter session by its own particles, replayed from its kept inputs
        (``server.estimation.replay``)."""
        return self.track_marked(principal, session_id, smoothed, smoother)[0]

    def track_marked(
        self, principal: Principal, session_id: str, smoothed: bool = False, smoother: Smoother = "rts",
    ) -> tuple[list[Estimate], dict[int, GateMarks]]:
        """The track (smoothed or not, ``track``) and, by index, what the innovation gate refused at its
        scan estimates (their fix or landmark snap; from the stored batch answers). ``Invalid`` when the
        particles are asked of a session that has none, ``Conflict`` when its kept inputs do not
        reproduce its track."""
        particles = smoothed and smoother == "particles"
        with self.db.transaction() as s:
            row = _visible(store.feed_state(s.connection(), session_id), principal, session_id)
            filter = str(row.state.get("filter", ""))
            if particles and not replays(filter):
                raise Invalid([{"field": "smoother", "msg": f"smoother=particles needs a particle-filter session "
                                                            f"(pf, pf-xy); session {session_id} is {filter}"}])
            if particles and row.last_seq + 1 > MAX_REPLAY_BATCHES:
                raise Conflict([{"field": "smoother", "msg": (
                    f"session {session_id} has {row.last_seq + 1} batches; smoother=particles replays at most "
                    f"{MAX_REPLAY_BATCHES}: only smoother=rts can smooth it")}])
            key = (session_id, row.last_seq, row.site_revision)
            cached = self._particle_tracks.get(key) if particles else None
            if cached is not None:
                return cached, store.gate_marks(s, session_id)
            track, states = store.track_with_states(s, session_id) if smoothed else (store.track(s, session_id), None)
            marks = store.gate_marks(s, session_id)
            kept = store.replay_inputs(s, session_id) if particles else None
        if not smoothed:
            return track, marks
        # the site as the batches use it (its context, cached by revision)
        site = self.sites.get(row.site_id, row.site_revision).map
        if kept is None:
            try:
                return smooth_track(track, site.walkable, states), marks
            except TrackerFailure as failure:  # (nothing is stored: the live track stays as it is)
                log.warning("session %s: %s", session_id, failure, exc_info=True)
                raise Conflict([{"field": "smoothed", "msg": f"session {session_id}: {failure}; its live track "
                                 "(smoothed=false) is unaffected"}]) from None
        by_replay = _replayed(*kept, site, track)
        if by_replay is None:
            raise Conflict([{"field": "smoother", "msg": (
                f"session {session_id}'s kept inputs do not reproduce its track (its site's plan or transmitters changed since, "
                "or it was stored before inputs were kept): only smoother=rts can smooth it")}])
        self._particle_tracks.put(key, by_replay)
        return by_replay, marks

    def track_page(
        self, principal: Principal, session_id: str, since: int, limit: int | None
    ) -> tuple[list[tuple[int, Estimate]], dict[int, GateMarks], bool]:
        """One page of the live track: (idx, estimate) after index ``since`` (at most ``limit``;
        all of them when None), the gate's marks on its scan estimates (``track_marked``), and
        whether more estimates follow the page (one row more is read to know)."""
        with self.db.transaction() as s:
            _visible(store.get_session(s, session_id), principal, session_id)
            rows = store.estimates_after(s, session_id, since, 2**62 if limit is None else limit + 1)
            more = limit is not None and len(rows) > limit
            page = rows[:limit] if more else rows
            marks = _marks_among(s, session_id, page)
        return page, marks, more

    def track_after(
        self, principal: Principal, session_id: str, after_idx: int, limit: int = 500
    ) -> tuple[SessionInfo, list[tuple[int, Estimate]], dict[int, GateMarks]]:
        """The session (as the caller may see it), its estimates after index ``after_idx`` (at
        most ``limit``) and the gate's marks on them (``track_marked``), for a live stream.
        The session is read first: when it is closed, the estimates read after it are all it
        will ever have (a closed session takes no batch)."""
        with self.db.transaction() as s:
            info = _visible(store.get_session(s, session_id), principal, session_id)
            rows = store.estimates_after(s, session_id, after_idx, limit)
            return info, rows, _marks_among(s, session_id, rows)

    def site_tracks_after(
        self, site_id: int, cursors: dict[str, int] | None, limit: int = 500
    ) -> tuple[dict[str, int], list[tuple[str, int, Estimate]], dict[tuple[str, int], GateMarks]]:
        """For a site's live stream (admin): its open sessions (id → track length), the
        estimates after each cursor (session id → last index sent), and the gate's marks on them
        by (session, index) (``track_marked``). Without cursors (a stream's first read)
        each open session's latest estimate; with cursors a session that has none starts at
        its first estimate, and a session that has one but is no longer open gets the
        estimates it had left."""
        with self.db.transaction() as s:
            if site_store.site_settings(s, site_id) is None:
                raise NotFound(f"site {site_id} does not exist")
            open_ = store.open_sessions_of_site(s, site_id)
            out: list[tuple[str, int, Estimate]] = []
            marks: dict[tuple[str, int], GateMarks] = {}
            ended = [] if cursors is None else [(sid, after) for sid, after in cursors.items() if sid not in open_]
            wanted = ended + [(sid, length - 2 if cursors is None else cursors.get(sid, -1))
                              for sid, length in sorted(open_.items())]
            for sid, after in wanted:
                if sid in open_ and open_[sid] - 1 <= after:
                    continue  # nothing new
                rows = store.estimates_after(s, sid, after, limit)
                out.extend((sid, idx, e) for idx, e in rows)
                marks.update(((sid, idx), m) for idx, m in _marks_among(s, sid, rows).items())
            return open_, out, marks

    def close(self, principal: Principal, session_id: str) -> None:
        """Closing is idempotent: closing a closed session is fine (204 again)."""
        with self.db.transaction() as s:
            _visible(store.get_session(s, session_id), principal, session_id)
            store.close_session(s, session_id)

    # -- feed --------------------------------------------------------------------------------
    def feed(self, principal: Principal, session_id: str, seq: int, steps: Sequence[Step], scans: Sequence[Scan]) -> BatchAnswer:
        """Apply the batch once; a seq already applied gets its stored answer again."""
        if len(steps) > MAX_BATCH_STEPS:
            raise TooLarge([{"field": "steps", "msg": f"{len(steps)} steps > {MAX_BATCH_STEPS} in one batch"}])
        if len(scans) > MAX_BATCH_SCANS:
            raise TooLarge([{"field": "scans", "msg": f"{len(scans)} scans > {MAX_BATCH_SCANS} in one batch"}])
        for _ in range(MAX_ATTEMPTS):
            # 1. read the session (no connection is held while computing, which may load a model)
            with self.db.read() as conn:
                row = _visible(store.feed_state(conn, session_id), principal, session_id)
                if seq <= row.last_seq:
                    answer = store.batch_answer(conn, session_id, seq)
                    if answer is None:
                        raise Conflict(
                            [{"field": "seq", "msg": f"seq {seq} is below the last applied seq {row.last_seq} "
                              "and was never applied; batches cannot be applied out of order"}]
                        )
                    return answer
            if row.status != "open":
                raise Conflict([{"field": "session", "msg": f"session {session_id} is closed"}])
            # 2. compute against that state
            site = self.sites.get(row.site_id, row.site_revision)
            est = SessionEstimator.from_dict(row.state)
            fixes = ModelFixes(self.positioning, row.site_id, row.model_id, site.active_model)
            recording = RecordingFixes(fixes) if replays(est.filter) else None
            try:
                outcome = est.apply_batch(
                    list(steps), list(scans), fixes if recording is None else recording,
                    site.map, crowdsourcing=bool(site.settings.get("crowdsourcing")),
                )
            except LateInputs as late:
                raise Invalid([
                    {"field": f"{i.kind}s.{i.index}.t", "msg": f"t {i.t} is before the session's last applied time {late.last_t}"}
                    for i in late.items[:100]
                ]) from None
            except TrackerFailure as failure:  # (the stored state is untouched: the phone can go on)
                log.warning("session %s, batch %s: %s", session_id, seq, failure, exc_info=True)
                raise Invalid([{"field": "batch", "msg": f"{failure}; nothing of this batch was applied and the "
                                "session is as it was: send the next batch"}]) from None
            answer = BatchAnswer(seq, outcome.estimate, outcome.applied_steps, outcome.applied_scans,
                                 outcome.skipped_scans, outcome.rejected_fixes, outcome.rejected_snaps)
            # 3. write it all in one transaction, if nobody applied a batch meanwhile
            with self.db.write() as conn:
                if store.save_batch(
                    conn, session_id, expected_last_seq=row.last_seq, state=est.to_dict(), answer=answer,
                    first_idx=row.track_length, estimates=outcome.estimates, init_t=outcome.init_t,
                    states=outcome.states,
                    inputs=None if recording is None else recording.batch(steps, scans, dict(site.map.grids)).to_dict(),
                ):
                    _crowdsource(conn, row.site_id, outcome.crowd)
                    return answer
            # lost the race (nothing was written): start over from the stored state
        raise Conflict([{"field": "session", "msg": "too many concurrent writers on this session; retry"}])


def _replayed(opening: dict | None, inputs: list[dict | None], site: SiteMap,
              track: list[Estimate]) -> list[Estimate] | None:
    """The track smoothed by replaying the session's kept inputs; None when some were not kept
    (stored before they were) or the replay does not reproduce the track."""
    if opening is None or any(i is None for i in inputs):
        return None
    try:
        batches = [RecordedBatch.from_dict(i) for i in inputs if i is not None]
    except (KeyError, TypeError, ValueError):
        return None
    return smoothed_by_replay(opening, batches, site, track)


def _marks_among(s: Session, session_id: str, rows: Sequence[tuple[int, Estimate]]) -> dict[int, GateMarks]:
    """The gate's marks on a run of consecutive track estimates (idx, estimate): only the
    batches that made them are read."""
    if not rows:
        return {}
    seqs = store.batch_seq_range(s, session_id, rows[0][0], rows[-1][0])
    return {} if seqs is None else store.gate_marks(s, session_id, seqs)


def _crowdsource(conn: Connection, site_id: int, candidates: Sequence[CrowdCandidate]) -> None:
    """Merge each confident (estimate, scan) into the nearest crowd point within 1 m of its floor, or insert it."""
    for c in candidates:
        p = c.point
        stored = store.nearby_crowd_points(conn, site_id, p.floor, p.x, p.y, CROWD_MERGE_RADIUS_M, p.building)
        target = find_merge_target([q for _, q in stored], p, CROWD_MERGE_RADIUS_M)
        if target is None:
            store.add_crowd_fingerprint(conn, site_id, p, c.scan.heading_deg, c.scan.t)
        else:
            fid, q = stored[target]
            store.update_crowd_fingerprint(conn, fid, merge_points(q, p))


def _reason(exc: ServiceError) -> str:
    """An error's messages as one line, for a skipped scan."""
    d = exc.detail
    if isinstance(d, list):
        return "; ".join(str(p.get("msg", p)) if isinstance(p, dict) else str(p) for p in d)
    return str(d)


def _visible(row: _Row | None, principal: Principal, session_id: str) -> _Row:
    """The session, if the caller may see it: its own device key, or any admin key. Others get
    404, so that session ids of other phones are not even confirmed to exist."""
    if row is None or (principal.scope != "admin" and row.owner_key != principal.key_hash):
        raise NotFound(f"session {session_id} does not exist")
    return row
