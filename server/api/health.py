"""Liveness that checks the database answers (no key needed)."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, status
from sqlalchemy import text

from server.api.deps import DB
from server.schemas import Health

router = APIRouter(tags=["service"])


@router.get("/healthz", response_model=Health, responses={503: {"description": "The database does not answer."}})
def healthz(db: DB) -> Health:
    try:
        with db.transaction() as s:
            s.execute(text("SELECT 1"))
    except Exception as exc:  # any driver error means "not healthy"
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, f"database unavailable: {type(exc).__name__}")
    return Health(status="ok")
