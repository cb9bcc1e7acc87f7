"""The FastAPI application factory."""

from __future__ import annotations

from contextlib import asynccontextmanager

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from server.api import health, locate, models, sessions, sites, surveys
from server.api.errors import InternalErrors
from server.api.limits import BodySizeLimit
from server.auth import Authenticator
from server.config import Settings, get_settings
from server.db import Database
from server.errors import ServiceError
from server.schemas import BatchIn, LocateIn, SurveyIn
from server.services.positioning import ModelCache, Positioning
from server.services.sessions import SessionService
from server.services.training import TrainingWorker


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the app for ``settings`` (default: from the environment). Migrations are not run here."""
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        if settings.embedded_worker:
            app.state.trainer = TrainingWorker(
                settings.database_url, settings.training_poll_s, settings.training_stale_after_s
            ).start()
        yield
        if app.state.trainer is not None:
            app.state.trainer.stop()
        app.state.db.dispose()

    app = FastAPI(
        title="Localizer",
        version="1.0.0",
        summary="Indoor positioning: RSS fingerprint surveys, models, locate and tracking sessions.",
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.db = Database(settings.database_url)
    app.state.auth = Authenticator(settings, app.state.db)
    app.state.positioning = Positioning(app.state.db, ModelCache(app.state.db, settings.model_cache_size))
    app.state.trainer = None
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_body_bytes)
    app.add_middleware(InternalErrors)  # outermost of ours: sees what the size limit lets through
    app.add_exception_handler(ServiceError, _service_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.state.sessions = SessionService(app.state.db, app.state.positioning)
    for module in (health, sites, surveys, models, locate, sessions):
        app.include_router(module.router)
    _document_own_bodies(app)
    return app


async def _service_error(_: Request, exc: ServiceError) -> JSONResponse:
    return JSONResponse({"detail": exc.detail}, status_code=exc.status_code)


async def _validation_error(_: Request, exc: RequestValidationError) -> JSONResponse:
    """422 naming each offending field, without echoing the (possibly huge) input back."""
    errors = []
    for err in exc.errors():
        loc = [p for p in err.get("loc", ()) if p != "[key]"]
        errors.append({"loc": loc, "field": ".".join(map(str, loc[1:])), "msg": err.get("msg"), "type": err.get("type")})
    return JSONResponse({"detail": errors}, status_code=422)


def _document_own_bodies(app: FastAPI) -> None:
    """The survey, batch and locate routes read their bodies themselves; publish the JSON schemas they enforce."""
    build = app.openapi

    def openapi() -> dict:
        if app.openapi_schema is None:
            schema = build()
            components = schema.setdefault("components", {}).setdefault("schemas", {})
            for model in (SurveyIn, BatchIn, LocateIn):
                body = model.model_json_schema(ref_template="#/components/schemas/{model}")
                components.update(body.pop("$defs", {}))
                components[model.__name__] = body
        return app.openapi_schema

    app.openapi = openapi
