"""Request dependencies: the caller's scope, and one ``Annotated`` alias per service.

Routes take their services as parameters (``sites: Sites``); the app builds each service
once (``server.app``), and tests swap one with ``app.dependency_overrides[provider]``.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, HTTPException, Path, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from starlette.concurrency import run_in_threadpool

from server import config
from server.auth import Principal, Scope
from server.services.health import HealthService
from server.services.models import ModelService
from server.services.positioning import Positioning as PositioningService
from server.services.sessions import SessionService
from server.services.sites import SiteService
from server.services.surveys import SurveyService

_bearer = HTTPBearer(auto_error=False, description="An admin or device API key.")


async def _principal(
    request: Request, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]
) -> Principal:
    """Dependencies are async so a request makes no thread hops for them; only a key that is
    not a bootstrap key costs a database look-up, run in the thread pool."""
    if credentials is None or credentials.scheme.lower() != "bearer":
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            "missing API key: send 'Authorization: Bearer <key>'",
            headers={"WWW-Authenticate": "Bearer"},
        )
    auth = request.app.state.auth
    address = request.client.host if request.client is not None else ""
    principal = auth.bootstrap(credentials.credentials)
    if principal is None:
        wait = auth.failures.retry_after(address)
        if wait is not None:  # too many wrong keys from this address: no look-up
            raise HTTPException(status.HTTP_429_TOO_MANY_REQUESTS, f"too many failed authentications from "
                                f"{address}: try again in {wait} s", headers={"Retry-After": str(wait)})
        principal = await run_in_threadpool(auth.stored, credentials.credentials)
    if principal is None:
        auth.failures.failed(address)
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED, "unknown or revoked API key", headers={"WWW-Authenticate": "Bearer"}
        )
    return principal


def require(scope: Scope):
    async def check(principal: Annotated[Principal, Depends(_principal)]) -> Principal:
        if not principal.allows(scope):
            raise HTTPException(status.HTTP_403_FORBIDDEN, f"this endpoint needs an {scope} key")
        return principal

    return check


#: a stored row's id in a path: the range every backend's integer column holds (else 422, never a 500)
PathId = Annotated[int, Path(ge=-(2**31), le=2**31 - 1)]

Admin = Annotated[Principal, Depends(require("admin"))]
Device = Annotated[Principal, Depends(require("device"))]


# --- services (the providers are async: no thread hop to hand one out) -------------------------


async def app_settings(request: Request) -> config.Settings:
    return request.app.state.settings


async def site_service(request: Request) -> SiteService:
    return request.app.state.sites


async def survey_service(request: Request) -> SurveyService:
    return request.app.state.surveys


async def model_service(request: Request) -> ModelService:
    return request.app.state.models


async def positioning_service(request: Request) -> PositioningService:
    return request.app.state.positioning


async def session_service(request: Request) -> SessionService:
    return request.app.state.sessions


async def health_service(request: Request) -> HealthService:
    return request.app.state.health


Settings = Annotated[config.Settings, Depends(app_settings)]
Sites = Annotated[SiteService, Depends(site_service)]
Surveys = Annotated[SurveyService, Depends(survey_service)]
Models = Annotated[ModelService, Depends(model_service)]
Positioning = Annotated[PositioningService, Depends(positioning_service)]
Sessions = Annotated[SessionService, Depends(session_service)]
Health = Annotated[HealthService, Depends(health_service)]
