"""Tracking sessions: open, feed batches, read, close. Free of HTTP.

Every batch is applied exactly once. The session row is read without a lock, the batch
is computed, and the outcome (tracker state, last seq, the stored answer, the new
track estimates, crowd fingerprints) is written in one transaction that starts with a
compare-and-set on ``last_seq``; if another request applied a batch meanwhile the
write is abandoned and the request starts over (and finds its seq already answered,
when it was a duplicate). See ``repositories.save_batch``.

A batch costs two round trips to the database: one read (the session row with its
site's revision; the site's transmitters, settings, walls and serving model come from
the per-process ``SiteContexts`` while that revision holds) and one write transaction.
"""

from __future__ import annotations

import uuid
from dataclasses import dataclass
from typing import Any

from server import repositories as repo
from server.auth import Principal
from server.db import Database
from server.errors import Conflict, Invalid, NotFound, ServiceError, TooLarge
from server.estimation.fingerprint import cold_start_fix
from server.estimation.session import SessionEstimator, multilateration_fix, time_order
from server.estimation.tracking import gate, make_crowd_point, merge_points
from server.estimation.tracking.crowd import find_merge_target
from server.estimation.types import Fix, Scan, Step
from server.schemas import (
    MAX_BATCH_SCANS,
    MAX_BATCH_STEPS,
    BatchIn,
    BatchResult,
    EstimateOut,
    SessionIn,
    SessionOut,
    SkippedScan,
)
from server.services.site_context import SiteContext, SiteContexts

#: how often a feed starts over after losing the compare-and-set to a concurrent request
MAX_ATTEMPTS = 20
#: crowd fingerprints closer than this (same floor) are merged
CROWD_MERGE_RADIUS_M = 1.0


@dataclass
class _Outcome:
    answer: dict[str, Any]
    state: dict[str, Any]
    estimates: list[dict[str, Any]]
    crowd: list[tuple[dict[str, Any], Scan]]
    init_t: float | None = None


class SessionService:
    """``positioning`` is the fingerprint-model service (``locate``); without one, scans give no fix."""

    def __init__(self, db: Database, positioning: Any = None):
        self.db = db
        self.positioning = positioning
        self.sites = SiteContexts(db)

    # -- open / read / close ---------------------------------------------------------------
    def open(self, principal: Principal, body: SessionIn) -> SessionOut:
        session_id = str(uuid.uuid4())
        est = SessionEstimator(body.filter, seed=uuid.UUID(session_id).int % 2**32)
        with self.db.transaction() as s:
            if repo.site_settings(s, body.site_id) is None:
                raise NotFound(f"site {body.site_id} does not exist")
            if body.model_id is not None and repo.model_site(s, body.model_id) != body.site_id:
                raise Invalid([{"field": "model_id", "msg": f"model {body.model_id} is not a model of site {body.site_id}"}])
            estimates = []
            if body.initial is not None:
                init = body.initial
                levels = repo.floor_levels(s, body.site_id)
                if levels and init.floor not in levels:
                    raise Invalid([{"field": "initial.floor", "msg": f"floor {init.floor} is not a floor of this site {sorted(levels)}"}])
                walls = repo.floor_walls(s, body.site_id, init.floor)
                estimates.append(est.start([init.x, init.y], init.covariance, init.floor, walls, None, "init"))
            row = repo.add_tracking_session(
                s, session_id, body.site_id, principal.key_hash, body.filter, body.model_id, est.to_dict(),
                [{"seq": None, **e} for e in estimates],
            )
            return _session_out(row)

    def list(self, principal: Principal, site_id: int | None, status: str | None, limit: int) -> list[SessionOut]:
        """The caller's sessions (every session for an admin key), newest first."""
        owner = None if principal.scope == "admin" else principal.key_hash
        with self.db.transaction() as s:
            return [_session_out(row) for row in repo.list_tracking_sessions(s, owner, site_id, status, limit)]

    def get(self, principal: Principal, session_id: str) -> SessionOut:
        with self.db.transaction() as s:
            return _session_out(_owned(s, principal, session_id))

    def track(self, principal: Principal, session_id: str) -> list[EstimateOut]:
        with self.db.transaction() as s:
            _owned(s, principal, session_id)
            return [
                EstimateOut(t=e.t, x=e.x, y=e.y, floor=e.floor, covariance=e.covariance, source=e.source)
                for e in repo.track_estimates(s, session_id)
            ]

    def close(self, principal: Principal, session_id: str) -> None:
        """Closing is idempotent: closing a closed session is fine (204 again)."""
        with self.db.transaction() as s:
            _owned(s, principal, session_id)
            repo.close_tracking_session(s, session_id)

    # -- feed --------------------------------------------------------------------------------
    def feed(self, principal: Principal, session_id: str, batch: BatchIn) -> dict[str, Any]:
        """Apply the batch; answers the ``BatchResult`` as JSON-ready data (also what a replay gets)."""
        if len(batch.steps) > MAX_BATCH_STEPS:
            raise TooLarge([{"field": "steps", "msg": f"{len(batch.steps)} steps > {MAX_BATCH_STEPS} in one batch"}])
        if len(batch.scans) > MAX_BATCH_SCANS:
            raise TooLarge([{"field": "scans", "msg": f"{len(batch.scans)} scans > {MAX_BATCH_SCANS} in one batch"}])
        for _ in range(MAX_ATTEMPTS):
            # 1. read the session (no connection is held while computing, which may load a model)
            with self.db.read() as conn:
                row = _visible(repo.feed_state(conn, session_id), principal, session_id)
                if batch.seq <= row.last_seq:
                    answer = repo.batch_answer(conn, session_id, batch.seq)
                    if answer is None:
                        raise Conflict(
                            [{"field": "seq", "msg": f"seq {batch.seq} is below the last applied seq {row.last_seq} "
                              "and was never applied; batches cannot be applied out of order"}]
                        )
                    answer.setdefault("rejected_fixes", [])  # answers stored before the innovation gate
                    return answer
            if row.status != "open":
                raise Conflict([{"field": "session", "msg": f"session {session_id} is closed"}])
            # 2. compute against that state
            outcome = self._apply(row, batch, self.sites.get(row.site_id, row.site_revision))
            # 3. write it all in one transaction, if nobody applied a batch meanwhile
            with self.db.write() as conn:
                if repo.save_batch(
                    conn, session_id, expected_last_seq=row.last_seq, seq=batch.seq, state=outcome.state,
                    answer=outcome.answer, first_idx=row.track_length,
                    estimates=[{"seq": batch.seq, **e} for e in outcome.estimates], init_t=outcome.init_t,
                ):
                    if outcome.crowd:
                        self._crowdsource(conn, row.site_id, outcome.crowd)
                    return outcome.answer
            # lost the race (nothing was written): start over from the stored state
        raise Conflict([{"field": "session", "msg": "too many concurrent writers on this session; retry"}])

    def _apply(self, row, batch: BatchIn, site: SiteContext) -> _Outcome:
        """Compute the batch against the stored state (nothing is written here)."""
        est = SessionEstimator.from_dict(row.state)
        steps = [
            Step(t=p.t, length_m=p.length_m, heading_deg=p.heading_deg,
                 **{k: v for k, v in (("length_std_m", p.length_std_m), ("heading_std_deg", p.heading_std_deg)) if v is not None})
            for p in batch.steps
        ]
        scans = [Scan(t=c.t, rss=dict(c.rss), heading_deg=c.heading_deg) for c in batch.scans]
        if est.last_t is not None:
            late = [
                {"field": f"{kind}s.{i}.t", "msg": f"t {item.t} is before the session's last applied time {est.last_t}"}
                for kind, i, item in time_order(steps, scans)
                if item.t < est.last_t
            ]
            if late:
                raise Invalid(late[:100])
        beacons = site.beacons
        walls_of = lambda level: site.walls.get(level, [])  # noqa: E731
        estimates, crowd, skipped, rejected = [], [], [], []
        applied_steps = applied_scans = 0
        for kind, i, item in time_order(steps, scans):
            if kind == "step":
                e = est.step(item)
                if e is not None:
                    applied_steps += 1
                    estimates.append(e)
                continue
            try:
                fix = self._fix(row, item, est, site)
            except ServiceError as exc:
                skipped.append(SkippedScan(index=i, reason=_reason(exc)))
                est.advance(item.t)
                continue
            cold = not est.started
            e = est.scan(item, fix, beacons, walls_of)
            applied_scans += 1
            estimates.append(e)
            if est.rejected:
                rejected.append(SkippedScan(index=i, reason=est.rejected))
                continue
            # Crowdsourcing: a tight estimate that agrees with the model's own fix for the scan
            # (never the cold-start scan: there the estimate *is* the fix).
            if (
                site.settings.get("crowdsourcing")
                and not cold
                and e["floor"] == fix.floor
                and gate([e["x"], e["y"]], e["covariance"], fix.mean, item.rss)
            ):
                crowd.append((make_crowd_point(e["x"], e["y"], e["floor"], item.rss), item))
        answer = BatchResult(
            seq=batch.seq,
            estimate=est.estimate,
            applied_steps=applied_steps,
            applied_scans=applied_scans,
            skipped_scans=skipped,
            rejected_fixes=rejected,
        ).model_dump(mode="json")
        return _Outcome(answer, est.to_dict(), estimates, crowd, est.init_t)

    def _fix(self, row, scan: Scan, est: SessionEstimator, site: SiteContext) -> Fix:
        """The fingerprint fix of one scan (restricted to the tracker's search region, if any).

        The first fix of a session without ``initial`` is the cold-start fusion (DESIGN.md):
        fingerprint fix ⊕ multilateration from transmitters with known positions, weights
        exp(−d) normalised; either alone when the other is unavailable."""
        if not est.started:
            fingerprint, why = None, None
            try:
                fingerprint = self._locate(row, scan, est, site)
            except ServiceError as exc:
                why = exc
            ml = multilateration_fix(scan.rss, site.beacons, None if fingerprint is None else fingerprint.floor)
            if fingerprint is None and ml is None:
                raise why if why is not None else Invalid("no fix")
            return cold_start_fix(fingerprint, ml)
        return self._locate(row, scan, est, site)

    def _locate(self, row, scan: Scan, est: SessionEstimator, site: SiteContext) -> Fix:
        if self.positioning is None:
            raise Conflict("no fingerprint model service is configured")
        near = radius = None
        region = est.search_region()
        if region is not None:
            x0, y0, x1, y1 = region
            near = ((x0 + x1) / 2, (y0 + y1) / 2)
            radius = max(x1 - x0, y1 - y0) / 2
        located = self.positioning.locate(
            row.site_id, scan.rss, heading_deg=scan.heading_deg, model_id=row.model_id, near=near, radius_m=radius,
            serving=site.active_model if row.model_id is None else None,
        )
        return located.fix

    def _crowdsource(self, conn, site_id: int, points: list[tuple[dict[str, Any], Scan]]) -> None:
        """Merge each confident (estimate, scan) into the nearest crowd point within 1 m, or insert it."""
        for point, scan in points:
            rows = repo.nearby_crowd_points(conn, site_id, point["floor"], point["x"], point["y"], CROWD_MERGE_RADIUS_M)
            stored = [{"x": r.x, "y": r.y, "floor": r.floor, "count": r.samples, "rss": r.rss} for r in rows]
            target = find_merge_target(stored, point, CROWD_MERGE_RADIUS_M)
            if target is None:
                repo.add_crowd_fingerprint(conn, site_id, point, scan.heading_deg, scan.t, device=None)
            else:
                repo.update_crowd_fingerprint(conn, rows[target].id, merge_points(stored[target], point))


def _owned(s, principal: Principal, session_id: str):
    return _visible(repo.get_tracking_session(s, session_id), principal, session_id)


def _visible(row, principal: Principal, session_id: str):
    """The session row, if the caller may see it: its own device key, or any admin key. Others get
    404, so that session ids of other phones are not even confirmed to exist."""
    if row is None or (principal.scope != "admin" and row.owner_key != principal.key_hash):
        raise NotFound(f"session {session_id} does not exist")
    return row


def _session_out(row) -> SessionOut:
    estimate = (row.state or {}).get("estimate")
    return SessionOut(
        id=row.id,
        site_id=row.site_id,
        filter=row.filter,
        model_id=row.model_id,
        status=row.status,
        estimate=estimate,
        created_at=row.created_at,
        last_seq=row.last_seq,
        track_length=row.track_length,
    )


def _reason(exc: ServiceError) -> str:
    d = exc.detail
    return d if isinstance(d, str) else str(d)


