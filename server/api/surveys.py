"""Survey upload (admin): JSON, CSV or UJIIndoorLoc CSV, stored in one transaction."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Header, Query, Request, Response, status
from starlette.concurrency import run_in_threadpool

from server.api.deps import Admin, PathId, Surveys
from server.api.fastpath import json_body_doc
from server.schemas import SurveyIn, SurveyResult

router = APIRouter(prefix="/api/v1/sites", tags=["surveys"])

_BODY_DOC = json_body_doc(SurveyIn)
_BODY_DOC["requestBody"]["content"]["text/csv"] = {
    "schema": {"type": "string"},
    "example": "x,y,floor,heading_deg,label,device,t,wifi:aa:bb:cc:dd:ee:ff,ble:lib-01\n"
    "1.5,2.0,0,90,A1,pixel,0.0,-61,-70\n",
}


@router.post(
    "/{site_id}/surveys",
    status_code=status.HTTP_201_CREATED,
    response_model=SurveyResult,
    openapi_extra=_BODY_DOC,
    responses={
        200: {"description": "Dry run, or a replay of an upload with the same Idempotency-Key.", "model": SurveyResult},
        409: {"description": "The Idempotency-Key was used before with another request."},
        413: {"description": "Too many fingerprints, or too large a body."},
        415: {"description": "Neither JSON nor CSV."},
        422: {"description": "Invalid rows: each error names the row (and CSV line) and the field; nothing stored."},
    },
)
async def upload_survey(
    site_id: PathId,
    request: Request,
    response: Response,
    surveys: Surveys,
    _: Admin,
    format: Annotated[Literal["json", "csv", "ujiindoorloc"] | None, Query()] = None,
    dry_run: Annotated[bool, Query(description="Validate and count only; store nothing.")] = False,
    idempotency_key: Annotated[
        str | None,
        Header(max_length=200, description="A retried upload with the same key is stored once; "
               "the key with another body is 409."),
    ] = None,
    source: Annotated[str | None, Query(min_length=1, max_length=200, pattern=r"^[\x21-\x7e]+$",
                                        description="Names the file this body is a part of: rows of the file "
                                        "that an earlier upload stored are not stored again.")] = None,
    first_row: Annotated[int, Query(ge=0, le=2**31 - 1, description="The file's data row (0-based, under "
                                    "the header) that is this body's first row (with `source`).")] = 0,
) -> SurveyResult:
    body = await request.body()
    outcome = await run_in_threadpool(
        surveys.ingest,
        site_id,
        body,
        request.headers.get("content-type", ""),
        format,
        idempotency_key=idempotency_key,
        dry_run=dry_run,
        source=source,
        first_row=first_row,
    )
    if outcome.replayed or dry_run:
        response.status_code = status.HTTP_200_OK
    if outcome.replayed:
        response.headers["Idempotent-Replay"] = "true"
    return SurveyResult(
        accepted=outcome.accepted,
        reference_points=outcome.reference_points,
        new_reference_points=outcome.new_reference_points,
        skipped=outcome.skipped,
        already_stored=outcome.already_stored,
        dry_run=outcome.dry_run,
    )
