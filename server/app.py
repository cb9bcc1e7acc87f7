"""The FastAPI application factory."""

from __future__ import annotations

import logging
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy.exc import DataError, OperationalError

from server.api import dashboard, events, floorplans, health, locate, models, sessions, sites, surveys
from server.api.errors import InternalErrors
from server.api.limits import BATCH_ROUTE, LOCATE_ROUTE, BodySizeLimit
from server.api.locate import LocateFastPath
from server.api.sessions import BatchFastPath
from server.auth import Authenticator
from server.config import Settings, get_settings
from server.db import Database
from server.errors import (
    Conflict,
    Invalid,
    InvalidField,
    NoReadyModel,
    NotFound,
    ServiceError,
    TooLarge,
    Unavailable,
    UnsupportedMedia,
)
from server.schemas import BatchIn, LocateIn, SurveyIn
from server.services.floorplans import FloorPlanService
from server.services.health import HealthService
from server.services.models import ModelService
from server.services.positioning import ModelCache, Positioning
from server.services.sessions import SessionService
from server.services.sites import SiteService
from server.services.surveys import SurveyService
from server.services.training import TrainingWorker

log = logging.getLogger("server")


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the app for ``settings`` (default: from the environment). Migrations are not run here."""
    settings = settings or get_settings()

    trainer = (
        TrainingWorker(settings.database_url, settings.training_poll_s, settings.training_stale_after_s)
        if settings.embedded_worker
        else None
    )

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        if trainer is not None:
            trainer.start()
        yield
        if trainer is not None:
            trainer.stop()
        app.state.db.dispose()

    app = FastAPI(
        title="Localizer",
        version="1.0.0",
        summary="Indoor positioning: RSS fingerprint surveys, models, locate and tracking sessions.",
        lifespan=lifespan,
        docs_url=None,  # served offline by server.api.dashboard
        redoc_url=None,
    )
    db = Database(settings.database_url, busy_timeout_s=settings.sqlite_busy_timeout_s)
    app.state.settings = settings
    app.state.db = db
    app.state.auth = Authenticator(settings, db)
    app.state.trainer = trainer
    # the services the routes get through ``server.api.deps``
    app.state.positioning = Positioning(db, ModelCache(db, settings.model_cache_size))
    app.state.sessions = SessionService(db, app.state.positioning)
    app.state.sites = SiteService(db)
    app.state.surveys = SurveyService(db, settings.max_survey_rows)
    app.state.models = ModelService(db, on_queued=None if trainer is None else trainer.wake)
    app.state.health = HealthService(db)
    app.state.floorplans = FloorPlanService(db)
    app.state.locate_fast_path = True  # see LocateFastPath
    app.add_middleware(LocateFastPath)  # innermost of ours: inside the size limit and the 500 guard
    app.state.batch_fast_path = True  # see BatchFastPath
    app.add_middleware(BatchFastPath)  # beside LocateFastPath (each passes on what is not its route)
    app.add_middleware(
        BodySizeLimit, max_bytes=settings.max_body_bytes, read_timeout_s=settings.body_read_timeout_s,
        routes=[(BATCH_ROUTE, int(settings.max_batch_body_kb * 1024)), (LOCATE_ROUTE, int(settings.max_locate_body_kb * 1024))],
    )
    app.add_middleware(InternalErrors)  # outermost of ours: sees what the size limit lets through
    app.add_exception_handler(ServiceError, _service_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(OperationalError, _database_unavailable)
    app.add_exception_handler(DataError, _unstorable)
    app.add_exception_handler(OverflowError, _unstorable)
    for module in (health, sites, floorplans, surveys, models, locate, sessions, events):
        app.include_router(module.router)
    dashboard.install(app)  # the dashboard at / and the docs, with their assets (no CDN)
    _document_own_bodies(app)
    return app


#: the HTTP status of each domain error (the nearest class in its MRO decides)
STATUS: dict[type[ServiceError], int] = {
    ServiceError: 400,
    NotFound: 404,
    Conflict: 409,
    TooLarge: 413,
    UnsupportedMedia: 415,
    Invalid: 422,
    Unavailable: 503,
}


def status_of(exc: ServiceError) -> int:
    return next(STATUS[cls] for cls in type(exc).__mro__ if cls in STATUS)


def detail_of(exc: ServiceError) -> Any:
    """The body's ``detail``: the error's own, with where an invalid field was in the request and
    how to get a model added. A 422's detail is a list of errors as the OpenAPI document publishes
    them (``loc``, ``msg``, ``type``), plus the error's own keys (``row``, ``field``, ``line``)."""
    if isinstance(exc, InvalidField):
        return [{"loc": ["body", exc.field], "field": exc.field, "msg": exc.msg, "type": "value_error"}]
    if isinstance(exc, NoReadyModel):
        return f"{exc.detail}: train one with POST /api/v1/sites/{exc.site_id}/models"
    if isinstance(exc, Invalid):
        return validation_errors(exc.detail)
    return exc.detail


def validation_errors(detail: Any) -> list[dict[str, Any]]:
    """``detail`` (a message, or a list of problems naming their ``row`` and ``field``) as the
    published 422 schema's list of ``{loc, msg, type}``."""
    errors = []
    for item in detail if isinstance(detail, list) else [detail]:
        error = dict(item) if isinstance(item, dict) else {"msg": str(item)}
        if "loc" not in error:
            row, field = error.get("row"), error.get("field")
            error["loc"] = ["body", *([row] if isinstance(row, int) else []), *([str(field)] if field else [])]
        error["msg"] = str(error.get("msg", "invalid"))
        error.setdefault("type", "value_error")
        errors.append(error)
    return errors


async def _service_error(_: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, ServiceError)  # registered for ServiceError only
    status = status_of(exc)
    headers = {"Retry-After": str(RETRY_AFTER_S)} if status == 503 else None
    return JSONResponse({"detail": detail_of(exc)}, status_code=status, headers=headers)


async def _validation_error(_: Request, exc: Exception) -> JSONResponse:
    """422 naming each offending field, without echoing the (possibly huge) input back."""
    assert isinstance(exc, RequestValidationError)  # registered for RequestValidationError only
    errors = []
    for err in exc.errors():
        loc = [p for p in err.get("loc", ()) if p != "[key]"]
        errors.append({"loc": loc, "field": ".".join(map(str, loc[1:])), "msg": err.get("msg"), "type": err.get("type")})
    return JSONResponse({"detail": errors}, status_code=422)


#: seconds a client is asked to wait when the database cannot write (full, locked, gone)
RETRY_AFTER_S = 5


async def _database_unavailable(_: Request, exc: Exception) -> JSONResponse:
    """The database cannot do the work now (disk full, locked too long, connection gone): 503 and
    when to try again, never a 500. Nothing was stored (the transaction rolled back)."""
    log.warning("database unavailable: %s", exc)
    return JSONResponse({"detail": f"the database is unavailable ({type(getattr(exc, 'orig', exc)).__name__}); "
                                   "nothing was stored, try again later"},
                        status_code=503, headers={"Retry-After": str(RETRY_AFTER_S)})


async def _unstorable(_: Request, exc: Exception) -> JSONResponse:
    """A value the database cannot hold (a number beyond its integer range, a NUL character)."""
    return JSONResponse({"detail": validation_errors(
        "a value of the request cannot be stored (a number beyond the database's range, or a NUL character)")},
        status_code=422)


def _document_own_bodies(app: FastAPI) -> None:
    """The survey, batch and locate routes read their bodies themselves; publish the JSON schemas they enforce."""
    build = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is not None:
            return app.openapi_schema
        schema = build()  # also kept as app.openapi_schema: completed in place, once
        components = schema.setdefault("components", {}).setdefault("schemas", {})
        for model in (SurveyIn, BatchIn, LocateIn):
            body = model.model_json_schema(ref_template="#/components/schemas/{model}")
            components.update(body.pop("$defs", {}))
            components[model.__name__] = body
        return schema

    app.openapi = openapi  # type: ignore[method-assign]  # FastAPI's documented way to extend the schema
