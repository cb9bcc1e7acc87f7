"""Live streams (server-sent events) of tracking sessions: one session's, or a whole site's.

Replicas share only the database, so a stream polls the store by track index (every
``events_poll_s``, 0.5 s by default): it sees the batches any server process applied, on
SQLite and on PostgreSQL alike. sse-starlette does the framing, the heartbeat comment
(every ``events_heartbeat_s``, 15 s by default) and notices a client that went away.
Both intervals are attributes of ``app.state`` (tests shorten them).

Browsers' ``EventSource`` cannot send an ``Authorization`` header; the dashboard reads
these streams with ``fetch`` instead.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from typing import Annotated, Any

import orjson
from fastapi import APIRouter, Header, Request
from sse_starlette import EventSourceResponse, ServerSentEvent
from starlette.concurrency import run_in_threadpool

from server.api.deps import Admin, Device, Sessions
from server.api.sessions import track_estimate_json
from server.auth import Principal
from server.domain import GateMarks
from server.errors import NotFound
from server.estimation.types import Estimate
from server.services.sessions import SessionService

router = APIRouter(tags=["live"])

#: most estimates read by one poll (a stream that is behind reads again at once)
BATCH = 500
DEFAULT_POLL_S = 0.5
DEFAULT_HEARTBEAT_S = 15.0

_STREAM_DOC: dict[int | str, dict[str, Any]] = {
    200: {"description": "A `text/event-stream`.", "content": {"text/event-stream": {}}},
}


def _interval(request: Request, name: str, default: float) -> float:
    return float(getattr(request.app.state, name, default))


def _json(value: dict[str, Any]) -> str:
    return orjson.dumps(value).decode()


def _estimate_data(idx: int, e: Estimate, marks: GateMarks | None, session_id: str | None = None) -> str:
    data = track_estimate_json(e, marks)  # the gate's marks as on the track
    data["idx"] = idx
    if session_id is not None:
        data["session_id"] = session_id
    return _json(data)


def _response(request: Request, events: AsyncIterator[ServerSentEvent]) -> EventSourceResponse:
    return EventSourceResponse(
        events,
        ping=_interval(request, "events_heartbeat_s", DEFAULT_HEARTBEAT_S),
        ping_message_factory=lambda: ServerSentEvent(comment="heartbeat"),
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )


@router.get(
    "/api/v1/sessions/{session_id}/events",
    response_class=EventSourceResponse,
    responses={**_STREAM_DOC, 404: {"description": "No such session, or it was opened with another device key."}},
)
async def session_events(
    session_id: str,
    request: Request,
    sessions: Sessions,
    principal: Device,
    last_event_id: Annotated[
        int | None, Header(alias="Last-Event-ID", ge=-1, description="Resume after this track index.")
    ] = None,
) -> EventSourceResponse:
    """The session's track as it grows (extension). One event `estimate` per track estimate,
    from the first one (or after `Last-Event-ID`): its `data` the Estimate JSON plus `idx`, its
    index in the track, which is also the event's `id`, and `fix_refused: true` on a scan whose
    fix the innovation gate refused, `snap_refused: true` on one whose landmark snap it refused (as on
    the track). An event `closed` (data
    `{"session_id", "track_length"}`) ends the stream when the session is closed. A comment
    line is sent as a heartbeat every 15 s. Same visibility as `GET /sessions/{id}`."""
    await run_in_threadpool(sessions.get, principal, session_id)  # 404 before the stream starts
    after = -1 if last_event_id is None else last_event_id
    return _response(request, _session_stream(request, sessions, principal, session_id, after))


async def _session_stream(
    request: Request, sessions: SessionService, principal: Principal, session_id: str, after: int
) -> AsyncIterator[ServerSentEvent]:
    poll = _interval(request, "events_poll_s", DEFAULT_POLL_S)
    while True:
        try:
            info, rows, marks = await run_in_threadpool(sessions.track_after, principal, session_id, after, BATCH)
        except NotFound:  # its site was deleted meanwhile
            return
        for idx, e in rows:
            yield ServerSentEvent(_estimate_data(idx, e, marks.get(idx)), event="estimate", id=str(idx))
            after = idx
        if len(rows) == BATCH:
            continue
        if info.status == "closed":
            yield ServerSentEvent(_json({"session_id": session_id, "track_length": after + 1}), event="closed")
            return
        await asyncio.sleep(poll)


@router.get(
    "/api/v1/sites/{site_id}/events",
    response_class=EventSourceResponse,
    responses={**_STREAM_DOC, 404: {"description": "Unknown site."}},
)
async def site_events(site_id: int, request: Request, sessions: Sessions, _: Admin) -> EventSourceResponse:
    """Every open session's estimates on the site as they come (extension, admin): the stream
    starts with each open session's latest estimate, then sends every new one; a session
    opened later is sent from its first estimate. Events `estimate` (the Estimate JSON plus
    `idx` and `session_id`) and `closed` (`{"session_id"}`) when a session is closed; a comment
    heartbeat every 15 s. Events carry no `id`: a reconnecting client starts afresh."""
    first = await run_in_threadpool(sessions.site_tracks_after, site_id, None)  # 404 before the stream starts
    return _response(request, _site_stream(request, sessions, site_id, first))


async def _site_stream(
    request: Request, sessions: SessionService, site_id: int,
    first: tuple[dict[str, int], list[tuple[str, int, Estimate]], dict[tuple[str, int], GateMarks]],
) -> AsyncIterator[ServerSentEvent]:
    poll = _interval(request, "events_poll_s", DEFAULT_POLL_S)
    open_, rows, marks = first
    cursors = {sid: length - 2 for sid, length in open_.items()}  # the last index sent per session
    while True:
        for sid, idx, e in rows:
            yield ServerSentEvent(_estimate_data(idx, e, marks.get((sid, idx)), sid), event="estimate")
            cursors[sid] = idx
        for sid in [s for s in cursors if s not in open_]:
            del cursors[sid]
            yield ServerSentEvent(_json({"session_id": sid}), event="closed")
        if len(rows) < BATCH:
            await asyncio.sleep(poll)
        try:
            open_, rows, marks = await run_in_threadpool(sessions.site_tracks_after, site_id, dict(cursors), BATCH)
        except NotFound:  # the site was deleted
            return
