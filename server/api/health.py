"""Liveness that checks the database answers (no key needed)."""

from __future__ import annotations

from fastapi import APIRouter

from server import schemas
from server.api.deps import Health

router = APIRouter(tags=["service"])


@router.get("/healthz", response_model=schemas.Health, responses={503: {"description": "The database does not answer."}})
def healthz(health: Health) -> schemas.Health:
    health.check()
    return schemas.Health(status="ok")
