"""Tracking sessions (device scope; admin keys may do the same and read every session)."""

from __future__ import annotations

from functools import partial

from fastapi import APIRouter, Request, Response, status
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import ValidationError
from starlette.concurrency import run_in_threadpool

from server.api.deps import Device
from server.schemas import BatchIn, BatchResult, EstimateOut, SessionIn, SessionOut
from server.services.sessions import SessionService

router = APIRouter(prefix="/api/v1/sessions", tags=["sessions"])

_NOT_YOURS = {404: {"description": "No such session, or it was opened with another device key."}}
_BATCH_BODY = {"requestBody": {"required": True, "content": {"application/json": {"schema": {"$ref": "#/components/schemas/BatchIn"}}}}}


def _service(request: Request) -> SessionService:
    return request.app.state.sessions


@router.post("", status_code=status.HTTP_201_CREATED, response_model=SessionOut,
             responses={404: {"description": "Unknown site."}, 422: {"description": "Bad filter, model or initial."}})
def open_session(body: SessionIn, request: Request, principal: Device) -> SessionOut:
    return _service(request).open(principal, body)


@router.post(
    "/{session_id}/batches",
    response_model=BatchResult,
    openapi_extra=_BATCH_BODY,
    responses={
        **_NOT_YOURS,
        409: {"description": "Session closed, or a seq below the last applied one that was never applied."},
        413: {"description": "More than 1,000 steps or scans in one batch."},
        422: {"description": "Invalid step or scan (names the field), or a time before the last applied one."},
    },
)
async def post_batch(session_id: str, request: Request, principal: Device) -> Response:
    """Apply a batch once; a batch whose seq was already applied gets the stored answer again.

    The hottest route reads its body itself: pydantic parses and validates the JSON in one
    pass, and the answer (plain JSON, as stored for replays) is sent as it is."""
    try:
        batch = BatchIn.model_validate_json(await request.body())
    except ValidationError as exc:
        raise RequestValidationError(
            [{**e, "loc": ("body", *e["loc"])} for e in exc.errors(include_url=False, include_input=False)]
        ) from None
    feed = partial(_service(request).feed, principal, session_id, batch)
    # On SQLite the batch is applied right here on the event loop: its database calls are
    # local file accesses of a fraction of a millisecond, and handing it to a thread costs
    # more CPU than that (GIL hand-offs); a networked database's waits go to the thread pool.
    return JSONResponse(feed() if request.app.state.db.embedded else await run_in_threadpool(feed))


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
