"""Liveness (the database answers) and readiness (it can write); no key needed."""

from __future__ import annotations

from fastapi import APIRouter

from server import schemas
from server.api.deps import Health

router = APIRouter(tags=["service"])


@router.get("/healthz", response_model=schemas.Health, responses={503: {"description": "The database does not answer."}})
def healthz(health: Health) -> schemas.Health:
    health.check()
    return schemas.Health(status="ok")


@router.get("/readyz", response_model=schemas.Health,
            responses={503: {"description": "The database cannot write (full, locked, read-only or gone); "
                             "see Retry-After."}})
def readyz(health: Health) -> schemas.Health:
    """Readiness: the database answers and commits a (harmless) write."""
    health.check_writable()
    return schemas.Health(status="ok")
