"""Locate (device): one scan in, a position with covariance and floor out.

The route below is the reference and what the OpenAPI document publishes; a request that
goes well is usually answered by ``server.api.fastpath.LocateFastPath`` in front of the
router, with the same work and the same bytes (``answer_bytes``), and every other request
(an error of any kind) by this route."""

from __future__ import annotations

import re

from fastapi import APIRouter, Request, Response
from starlette.types import ASGIApp, Receive, Scope, Send

from server.api.deps import Device, PathId, Positioning
from server.api.fastpath import (
    BodyUnread,
    declared_json,
    json_body_doc,
    key_principal,
    read_body,
    read_json,
    replaying,
    run_blocking,
    run_work,
)
from server.domain import Located
from server.schemas import CandidateOut, LocateIn, LocateOut

router = APIRouter(prefix="/api/v1/sites", tags=["locate"])


@router.post(
    "/{site_id}/locate",
    response_model=LocateOut,
    openapi_extra=json_body_doc(LocateIn),
    responses={409: {"description": "The site has no ready model."},
               422: {"description": "No transmitter of the scan is known to the model."}},
)
async def locate(site_id: PathId, request: Request, positioning: Positioning, _: Device) -> Response:
    body = await read_json(request, LocateIn)
    located = await run_blocking(request, positioning.locate_answer, site_id, body.rss, body.heading_deg, body.model_id)
    return Response(answer_bytes(located), media_type="application/json")


def answer_bytes(located: Located) -> bytes:
    """The response body for a fix (pydantic's serialiser: the same bytes as FastAPI's, ≈ 3× faster)."""
    fix, coverage = located.fix, located.coverage
    return LocateOut(
        x=fix.x, y=fix.y, floor=fix.floor, building=fix.building, covariance=fix.covariance.tolist(),
        model_id=located.model_id, algorithm=located.algorithm, reference_point=fix.reference_point,
        candidates=[CandidateOut(label=c.label, x=c.x, y=c.y, floor=c.floor, building=c.building,
                                 probability=c.probability)
                    for c in fix.candidates],
        in_coverage=None if coverage is None else coverage.inside,
        coverage_ratio=None if coverage is None else coverage.ratio,
    ).model_dump_json().encode()


#: the route's path, with a site id that ``PathId`` takes as it is (a plain 32-bit integer; any
#: other spelling goes to the route)
_LOCATE_PATH = re.compile(r"/api/v1/sites/(0|-?[1-9][0-9]{0,9})/locate")
_ID_MIN, _ID_MAX = -(2**31), 2**31 - 1


class LocateFastPath:
    """Pure ASGI middleware, the innermost of the app's own (inside the body-size limit): answers
    ``POST /api/v1/sites/{site_id}/locate`` itself when all goes well (a bearer key allowing device
    work, a JSON body of declared length that ``LocateIn`` accepts, a fix), with the route's own
    work and bytes but without FastAPI's per-request machinery: trying the routes in turn, solving
    the route's five dependencies, its exception and exit-stack wrappers (≈ 270 µs of CPU per fix
    measured in process, a quarter of a fix's total).

    Everything else — another route, no key or a refused one, a body not declared JSON or of no
    declared length, an invalid body, any error of the work, dependency overrides in place — goes
    to the app as it arrived (the body replayed), where the route answers exactly as it always did
    (running the read-only work again when it failed here). ``app.state.locate_fast_path = False``
    sends every request to the route."""

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        match = _LOCATE_PATH.fullmatch(scope["path"]) if scope["type"] == "http" and scope["method"] == "POST" \
            else None
        application = scope.get("app")
        if match is None or application is None or not getattr(application.state, "locate_fast_path", False) \
                or application.dependency_overrides or not declared_json(scope):
            await self.app(scope, receive, send)
            return
        try:
            messages, body_bytes = await read_body(receive)
        except BodyUnread as unread:  # a body too large, too slow, cut off: the route reports it
            await self.app(scope, replaying(unread.messages, unread.error, receive), send)
            return
        try:
            state = application.state
            principal = await key_principal(state.auth, scope)
            site_id = int(match.group(1))
            if principal is None or not principal.allows("device") or not _ID_MIN <= site_id <= _ID_MAX:
                raise _Unanswered
            body = LocateIn.model_validate_json(body_bytes)
            located = await run_work(state.db, state.positioning.locate_answer, site_id, body.rss, body.heading_deg,
                                     body.model_id)
            answer = answer_bytes(located)
        except Exception:  # noqa: BLE001  (refused, invalid or failed: the route answers, its own way)
            await self.app(scope, replaying(messages, None, receive), send)
            return
        await Response(answer, media_type="application/json")(scope, receive, send)


class _Unanswered(Exception):
    """This request is the route's to answer."""
