"""Fingerprint models (admin): train in the background, list, inspect, activate."""

from __future__ import annotations

from fastapi import APIRouter, Request, status

from server.api.deps import DB, Admin
from server.schemas import ModelIn, ModelOut
from server.services import models
from server.tables import Model

router = APIRouter(prefix="/api/v1/sites/{site_id}/models", tags=["models"])


def model_out(model: Model) -> ModelOut:
    out = ModelOut.model_validate(model, from_attributes=True)
    out.kinds = out.kinds or None
    return out


@router.post("", status_code=status.HTTP_202_ACCEPTED, response_model=ModelOut)
def train(site_id: int, body: ModelIn, request: Request, db: DB, _: Admin) -> ModelOut:
    """Queue a training job; poll the model until it is `ready` or `failed`."""
    model = models.queue_model(db, site_id, body)
    if (worker := request.app.state.trainer) is not None:
        worker.wake()
    return model_out(model)


@router.get("", response_model=list[ModelOut])
def list_models(site_id: int, db: DB, _: Admin) -> list[ModelOut]:
    return [model_out(m) for m in models.list_models(db, site_id)]


@router.get("/{model_id}", response_model=ModelOut)
def get_model(site_id: int, model_id: int, db: DB, _: Admin) -> ModelOut:
    return model_out(models.get_model(db, site_id, model_id))


@router.post("/{model_id}/activate", response_model=ModelOut, responses={409: {"description": "Model not ready."}})
def activate(site_id: int, model_id: int, db: DB, _: Admin) -> ModelOut:
    return model_out(models.activate(db, site_id, model_id))
