"""Tracking sessions (device scope; admin keys may do the same and read every session)."""

from __future__ import annotations

import asyncio
import re
import weakref
from functools import partial
from typing import Annotated, Any, Literal

import anyio.to_thread
import orjson
from anyio import CapacityLimiter
from fastapi import APIRouter, Query, Request, Response, status
from fastapi.responses import JSONResponse

from server.api.deps import Device, Sessions
from server.api.fastpath import FastPath, json_body_doc, read_json, run_work
from server.auth import Principal
from server.db import Database
from server.domain import BatchAnswer, GateMarks, SessionInfo
from server.errors import InvalidField
from server.estimation.types import Estimate, InitialHeading, Scan, ScanNote, Step
from server.schemas import (
    BatchIn,
    BatchResult,
    EstimateOut,
    SessionIn,
    SessionOut,
    SkippedScan,
    TrackEstimateOut,
)
from server.services.sessions import InitialPosition, SessionService

router = APIRouter(prefix="/api/v1/sessions", tags=["sessions"])

_NOT_YOURS: dict[int | str, dict[str, Any]] = {404: {"description": "No such session, or it was opened with another device key."}}


@router.post("", status_code=status.HTTP_201_CREATED, response_model=SessionOut, response_model_exclude_unset=True,
             responses={404: {"description": "Unknown site."}, 422: {"description": "Bad filter, model or initial."}})
def open_session(body: SessionIn, sessions: Sessions, principal: Device) -> SessionOut:
    init = body.initial
    initial = None if init is None else InitialPosition(
        init.x, init.y, init.floor, init.covariance, init.building,
        None if init.heading_deg is None or init.heading_std_deg is None
        else InitialHeading(init.heading_deg, init.heading_std_deg))
    return session_out(sessions.open(principal, body.site_id, body.filter, body.model_id, initial, body.seed,
                                    body.filter_params))


@router.post(
    "/{session_id}/batches",
    response_model=BatchResult,
    openapi_extra=json_body_doc(BatchIn),
    responses={
        **_NOT_YOURS,
        409: {"description": "Session closed, or a seq below the last applied one that was never applied."},
        413: {"description": "More than 1,000 steps or scans in one batch."},
        422: {"description": "Invalid step or scan (names the field), or a time before the last applied one."},
    },
)
async def post_batch(session_id: str, request: Request, sessions: Sessions, principal: Device) -> Response:
    """Apply a batch once; a batch whose seq was already applied gets the stored answer again.
    The answer is sent as stored (plain JSON), which is also what a replay gets. A batch that goes
    well is usually answered by ``BatchFastPath`` in front of the router, with this same work and bytes."""
    batch = await read_json(request, BatchIn)
    return batch_response(await feed_batch(request.app.state.db, sessions, principal, session_id, batch))


async def feed_batch(db: Database, sessions: SessionService, principal: Principal, session_id: str,
                     batch: BatchIn) -> BatchAnswer:
    """``sessions.feed`` of a parsed batch: on the event loop for an embedded database (SQLite), else in
    the thread pool, at most ``FEED_THREADS`` at once (the route and ``BatchFastPath`` both run this)."""
    steps = [
        Step(p.t, p.length_m, p.heading_deg, **{k: v for k, v in (("length_std_m", p.length_std_m),
                                                                  ("heading_std_deg", p.heading_std_deg)) if v is not None})
        for p in batch.steps
    ]
    scans = [Scan(c.t, dict(c.rss), c.heading_deg) for c in batch.scans]
    if db.embedded:
        return await run_work(db, sessions.feed, principal, session_id, batch.seq, steps, scans)
    return await anyio.to_thread.run_sync(partial(sessions.feed, principal, session_id, batch.seq, steps, scans),
                                          limiter=_feed_threads())


def batch_response(answer: BatchAnswer) -> Response:
    """A batch's answer as the route sends it."""
    return JSONResponse(batch_result(answer).model_dump(mode="json"))


#: batches a process computes at once on a networked database (each in a thread of its own while it
#: waits on the database); the rest wait their turn on the event loop. Dozens of threads taking turns
#: on the GIL cost more CPU per batch than the batches themselves need (≈ 0.8 ms a batch more at 32
#: at once than at 4 on PostgreSQL), and eight keep a process's share of the cores busy while the
#: database answers, within the connection pool's 30 (``server.db.make_engine``)
FEED_THREADS = 8
_feed_limiters: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, CapacityLimiter] = weakref.WeakKeyDictionary()


def _feed_threads() -> CapacityLimiter:
    """The event loop's own limiter (an ``anyio`` limiter belongs to one loop)."""
    loop = asyncio.get_running_loop()
    limiter = _feed_limiters.get(loop)
    if limiter is None:
        limiter = _feed_limiters[loop] = CapacityLimiter(FEED_THREADS)
    return limiter


@router.get("", response_model=list[SessionOut])
def list_sessions(
    sessions: Sessions,
    principal: Device,
    site_id: Annotated[int | None, Query(ge=-(2**31), le=2**31 - 1, description="Only this site's sessions.")] = None,
    status: Annotated[Literal["open", "closed"] | None, Query(description="Only open or only closed sessions.")] = None,
    limit: Annotated[int, Query(ge=1, le=1000, description="At most this many, newest first.")] = 100,
) -> Response:
    """The sessions opened with the caller's key (an admin key sees every session), newest
    first: a phone that restarts can find the session it was feeding."""
    body = [session_json(info) for info in sessions.list_sessions(principal, site_id, status, limit)]
    return Response(orjson.dumps(body, option=orjson.OPT_UTC_Z), media_type="application/json")


@router.get("/{session_id}", response_model=SessionOut, response_model_exclude_unset=True, responses=_NOT_YOURS)
def get_session(session_id: str, sessions: Sessions, principal: Device) -> SessionOut:
    return session_out(sessions.get(principal, session_id))


@router.get("/{session_id}/track", response_model=list[TrackEstimateOut], response_model_exclude_unset=True,
            responses=_NOT_YOURS)
def get_track(
    session_id: str,
    request: Request,
    sessions: Sessions,
    principal: Device,
    smoothed: Annotated[bool, Query(description=(
        "Extension. true: the track after a fixed-interval smoother (same length, times, floors and "
        "sources; each position uses the fixes after it too; `smoother` says which) — the best "
        "after-the-fact path, for replay and analytics; covariances calibrated like the live ones'; 409 if "
        "the smoother fails numerically on the stored track (the live track is unaffected). "
        "false (default): the live track as estimated."))] = False,
    smoother: Annotated[Literal["rts", "particles"], Query(description=(
        "Extension, with `smoothed=true`. `rts` (default): the RTS smoother over the stored estimates, for "
        "every filter (a `pf` session's steps through its cloud's own moments of each step, so walls shape "
        "the gain). `particles`: a `pf`/`pf-xy` session's own particles, smoothed along their ancestry "
        "(fixed-lag path-space smoother) by replaying the session's kept inputs — no better than `rts` on "
        "the README's figures, an independent second smoother; 422 for another filter, 409 "
        "when the session's kept inputs no longer reproduce its track (its site's plan or transmitters changed since, or it "
        "was stored before inputs were kept) or it has more than 10,000 batches."))] = "rts",
    since: Annotated[int | None, Query(ge=-1, le=2**31 - 1, description=(
        "Extension. Only the estimates whose track index (0 = the first) is greater than this: the index "
        "of the last estimate already read. Default: from the start."))] = None,
    limit: Annotated[int | None, Query(ge=1, le=10_000, description=(
        "Extension. At most this many estimates; when more remain, a `Link: <...>; rel=\"next\"` header "
        "gives the URL of the next page. Default: no limit (the whole rest of the track)."))] = None,
) -> Any:
    """The session's track, oldest first. A `scan` estimate whose fix the innovation gate refused
    carries the extension `fix_refused: true`, one whose landmark snap it refused `snap_refused: true`.
    With `since` and/or `limit` (extension) one page of the live track; they do not combine with
    `smoothed=true` (422)."""
    if smoother != "rts" and not smoothed:
        raise InvalidField("smoother", "smoother applies to smoothed=true only")
    if since is None and limit is None:
        track, marks = sessions.track_marked(principal, session_id, smoothed, smoother)
        return [track_estimate_out(e, marks.get(i)) for i, e in enumerate(track)]
    if smoothed:
        raise InvalidField("smoothed", "smoothed=true does not combine with since or limit: "
                                       "the smoothed track is read whole")
    page, marks, more = sessions.track_page(principal, session_id, -1 if since is None else since, limit)
    body = [track_estimate_json(e, marks.get(idx)) for idx, e in page]
    headers = {}
    if more and limit is not None:
        url = request.url.include_query_params(since=page[-1][0], limit=limit)
        headers["Link"] = f'<{url}>; rel="next"'
    return Response(orjson.dumps(body), media_type="application/json", headers=headers)


@router.delete("/{session_id}", status_code=status.HTTP_204_NO_CONTENT, responses=_NOT_YOURS)
def close_session(session_id: str, sessions: Sessions, principal: Device) -> Response:
    sessions.close(principal, session_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


def estimate_out(e: Estimate) -> EstimateOut:
    return EstimateOut(t=e.t, x=e.x, y=e.y, floor=e.floor, building=e.building,
                       covariance=[list(e.covariance[0]), list(e.covariance[1])], source=e.source)


def estimate_json(e: Estimate) -> dict[str, Any]:
    """``estimate_out(e)`` as JSON-ready data, built directly for the long lists (a track page,
    the live streams): 1,000 pydantic models cost ≈ 10 ms, these dicts ≈ 1.5 ms. Tests pin each
    ``*_json`` equal to its schema's dump."""
    return {"t": e.t, "x": e.x, "y": e.y, "floor": e.floor, "building": e.building,
            "covariance": [list(e.covariance[0]), list(e.covariance[1])], "source": e.source}


def track_estimate_json(e: Estimate, marks: GateMarks | None) -> dict[str, Any]:
    """``track_estimate_out(e, marks)`` as JSON-ready data (``estimate_json``)."""
    out = estimate_json(e)
    if marks is not None:
        out.update(marks.fields())
    return out


def session_json(info: SessionInfo) -> dict[str, Any]:
    """``session_out(info)`` as data for orjson: ``created_at`` stays a datetime and the estimate the
    `Estimate` dataclass, which orjson writes field by field in C (its fields are the schema's
    Estimate; a test pins the JSON equal to the schema's): 40 % of a 1,000-session list's encoding."""
    return {"id": info.id, "site_id": info.site_id, "filter": info.filter, "model_id": info.model_id,
            "status": info.status, "estimate": info.estimate, "created_at": info.created_at,
            "last_seq": info.last_seq, "track_length": info.track_length}


def track_estimate_out(e: Estimate, marks: GateMarks | None) -> TrackEstimateOut:
    """Every field set but the gate's marks (``fix_refused``, ``snap_refused``), each set only when
    true (the route leaves out unset fields)."""
    return TrackEstimateOut(t=e.t, x=e.x, y=e.y, floor=e.floor, building=e.building,
                            covariance=[list(e.covariance[0]), list(e.covariance[1])], source=e.source,
                            **(marks.fields() if marks is not None else {}))


def session_out(info: SessionInfo) -> SessionOut:
    """The schema's session; ``filter_params`` only when the session was given any (the routes leave out unset fields)."""
    return SessionOut(
        id=info.id, site_id=info.site_id, filter=info.filter, model_id=info.model_id, status=info.status,
        estimate=None if info.estimate is None else estimate_out(info.estimate), created_at=info.created_at,
        last_seq=info.last_seq, track_length=info.track_length,
        **({} if info.filter_params is None else {"filter_params": dict(info.filter_params)}),
    )


def _notes_out(notes: tuple[ScanNote, ...]) -> list[SkippedScan]:
    return [SkippedScan(index=n.index, reason=n.reason) for n in notes]


def batch_result(a: BatchAnswer) -> BatchResult:
    return BatchResult(
        seq=a.seq, estimate=None if a.estimate is None else estimate_out(a.estimate),
        applied_steps=a.applied_steps, applied_scans=a.applied_scans,
        skipped_scans=_notes_out(a.skipped_scans),
        rejected_fixes=_notes_out(a.rejected_fixes),
        rejected_snaps=_notes_out(a.rejected_snaps),
    )


#: the batch route's path, as the router matches it (a session id is any segment)
_BATCH_PATH = re.compile(r"/api/v1/sessions/([^/]+)/batches")


class BatchFastPath(FastPath):
    """``POST /api/v1/sessions/{session_id}/batches`` answered without FastAPI's machinery when all
    goes well (``FastPath``), with the route's own ``feed_batch`` and ``batch_response``. Nothing is
    stored before the key and the body have passed exactly the route's checks; when it fails the
    route answers its own way (a failed batch wrote nothing, and one stored meanwhile is answered
    from storage: batches are idempotent by seq)."""

    path = _BATCH_PATH
    flag = "batch_fast_path"

    async def answer(self, state: Any, match: re.Match[str], principal: Principal, body: bytes) -> Response:
        batch = BatchIn.model_validate_json(body)
        return batch_response(await feed_batch(state.db, state.sessions, principal, match.group(1), batch))
