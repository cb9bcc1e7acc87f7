"""Tracking sessions (device scope; admin keys may do the same and read every session)."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request, Response, status
from fastapi.responses import JSONResponse

from server.api.deps import Device
from server.api.fastpath import json_body_doc, read_json, run_blocking
from server.schemas import BatchIn, BatchResult, EstimateOut, SessionIn, SessionOut
from server.services.sessions import SessionService

router = APIRouter(prefix="/api/v1/sessions", tags=["sessions"])

_NOT_YOURS = {404: {"description": "No such session, or it was opened with another device key."}}


def _service(request: Request) -> SessionService:
    return request.app.state.sessions


@router.post("", status_code=status.HTTP_201_CREATED, response_model=SessionOut,
             responses={404: {"description": "Unknown site."}, 422: {"description": "Bad filter, model or initial."}})
def open_session(body: SessionIn, request: Request, principal: Device) -> SessionOut:
    return _service(request).open(principal, body)


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
async def post_batch(session_id: str, request: Request, principal: Device) -> Response:
    """Apply a batch once; a batch whose seq was already applied gets the stored answer again.
    The answer is sent as stored (plain JSON), which is also what a replay gets."""
    batch = await read_json(request, BatchIn)
    return JSONResponse(await run_blocking(request, _service(request).feed, principal, session_id, batch))


@router.get("", response_model=list[SessionOut])
def list_sessions(
    request: Request,
    principal: Device,
    site_id: Annotated[int | None, Query(description="Only this site's sessions.")] = None,
    status: Annotated[Literal["open", "closed"] | None, Query(description="Only open or only closed sessions.")] = None,
    limit: Annotated[int, Query(ge=1, le=1000, description="At most this many, newest first.")] = 100,
) -> list[SessionOut]:
    """The sessions opened with the caller's key (an admin key sees every session), newest
    first: a phone that restarts can find the session it was feeding."""
    return _service(request).list(principal, site_id, status, limit)


@router.get("/{session_id}", response_model=SessionOut, responses=_NOT_YOURS)
def get_session(session_id: str, request: Request, principal: Device) -> SessionOut:
    return _service(request).get(principal, session_id)


@router.get("/{session_id}/track", response_model=list[EstimateOut], responses=_NOT_YOURS)
def get_track(session_id: str, request: Request, principal: Device) -> list[EstimateOut]:
    return _service(request).track(principal, session_id)


@router.delete("/{session_id}", status_code=status.HTTP_204_NO_CONTENT, responses=_NOT_YOURS)
def close_session(session_id: str, request: Request, principal: Device) -> Response:
    _service(request).close(principal, session_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
