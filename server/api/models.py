"""Fingerprint models (admin): train in the background, list, inspect, activate."""

from __future__ import annotations

from fastapi import APIRouter, status

from server.api.deps import Admin, Models, PathId
from server.domain import ModelInfo, ModelSpec
from server.schemas import HeldOutPointErrorOut, ModelIn, ModelOut

router = APIRouter(prefix="/api/v1/sites/{site_id}/models", tags=["models"])


def model_out(model: ModelInfo) -> ModelOut:
    out = ModelOut.model_validate(model, from_attributes=True)
    out.kinds = out.kinds or None
    return out


@router.post("", status_code=status.HTTP_202_ACCEPTED, response_model=ModelOut)
def train(site_id: PathId, body: ModelIn, models: Models, _: Admin) -> ModelOut:
    """Queue a training job; poll the model until it is `ready` or `failed`. Whether it then
    becomes the active model follows `activate` (see `metrics.activation` for the decision)."""
    spec = ModelSpec(
        algorithm=body.algorithm, params=body.params, use_heading=body.use_heading, kinds=tuple(body.kinds or ()),
        include_crowd=body.include_crowd, activate=body.activate,
    )
    return model_out(models.queue(site_id, spec))


@router.get("", response_model=list[ModelOut])
def list_models(site_id: PathId, models: Models, _: Admin) -> list[ModelOut]:
    return [model_out(m) for m in models.list_models(site_id)]


@router.get("/{model_id}", response_model=ModelOut)
def get_model(site_id: PathId, model_id: PathId, models: Models, _: Admin) -> ModelOut:
    return model_out(models.get(site_id, model_id))


@router.get("/{model_id}/errors", response_model=list[HeldOutPointErrorOut],
            responses={409: {"description": "Model not ready."}})
def held_out_errors(site_id: PathId, model_id: PathId, models: Models, _: Admin) -> list[HeldOutPointErrorOut]:
    """Extension: each reference point of the model's held-out sample with its mean error (m),
    from training (at most 1,000 held-out scans, stratified by building and floor); empty for
    a model trained on too few fingerprints to validate."""
    return [HeldOutPointErrorOut.model_validate(p, from_attributes=True) for p in models.held_out_errors(site_id, model_id)]


@router.post("/{model_id}/activate", response_model=ModelOut, responses={409: {"description": "Model not ready."}})
def activate(site_id: PathId, model_id: PathId, models: Models, _: Admin) -> ModelOut:
    return model_out(models.activate(site_id, model_id))
