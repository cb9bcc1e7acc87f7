"""Request dependencies: the database and the caller's scope."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, HTTPException, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from starlette.concurrency import run_in_threadpool

from server.auth import Principal, Scope
from server.db import Database

_bearer = HTTPBearer(auto_error=False, description="An admin or device API key.")


async def database(request: Request) -> Database:
    """The app's database; routes open their transaction explicitly so it commits before they answer."""
    return request.app.state.db


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
    principal = auth.bootstrap(credentials.credentials) or await run_in_threadpool(auth.stored, credentials.credentials)
    if principal is None:
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


DB = Annotated[Database, Depends(database)]
Admin = Annotated[Principal, Depends(require("admin"))]
Device = Annotated[Principal, Depends(require("device"))]
