"""Survey upload (admin): JSON, CSV or UJIIndoorLoc CSV, stored in one transaction."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Header, Query, Request, Response, status
from starlette.concurrency import run_in_threadpool

from server.api.deps import DB, Admin
from server.api.fastpath import json_body_doc
from server.schemas import SurveyIn, SurveyResult
from server.services.surveys import ingest_survey

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
        413: {"description": "Too many fingerprints, or too large a body."},
        415: {"description": "Neither JSON nor CSV."},
        422: {"description": "Invalid rows: each error names the row (and CSV line) and the field; nothing stored."},
    },
)
async def upload_survey(
    site_id: int,
    request: Request,
    response: Response,
    db: DB,
    _: Admin,
    format: Annotated[Literal["json", "csv", "ujiindoorloc"] | None, Query()] = None,
    dry_run: Annotated[bool, Query(description="Validate and count only; store nothing.")] = False,
    idempotency_key: Annotated[
        str | None, Header(max_length=200, description="A retried upload with the same key is stored once.")
    ] = None,
) -> SurveyResult:
    body = await request.body()
    ingested = await run_in_threadpool(
        ingest_survey,
        db,
        site_id,
        body,
        request.headers.get("content-type", ""),
        format,
        max_rows=request.app.state.settings.max_survey_rows,
        idempotency_key=idempotency_key,
        dry_run=dry_run,
    )
    if ingested.replayed or dry_run:
        response.status_code = status.HTTP_200_OK
    if ingested.replayed:
        response.headers["Idempotent-Replay"] = "true"
    return ingested.result
