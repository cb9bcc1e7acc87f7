"""Fingerprint models: training jobs and their claims, artifacts, the active (serving) model.

At most one model per site is active (a partial unique index); activating one renews
the site's revision, since fixes depend on it.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any, cast

from sqlalchemy import Connection, bindparam, func, select, update
from sqlalchemy.orm import Session

from server.domain import ACTIVATIONS, Activation, Artifact, ModelInfo, ModelSpec, ModelStatus, ServingCandidate
from server.store._direct import DirectStatement
from server.store._results import changed
from server.store.sites import touch_site
from server.tables import Model, ModelArtifact


def _info(row: Model) -> ModelInfo:
    return ModelInfo(
        id=row.id, site_id=row.site_id, algorithm=row.algorithm, params=dict(row.params or {}),
        use_heading=row.use_heading, kinds=tuple(row.kinds or ()), include_crowd=row.include_crowd,
        status=cast(ModelStatus, row.status), error=row.error, active=row.active, trained_on=row.trained_on,
        # before training ends the JSON holds only the requested activation, not metrics
        metrics=dict(row.metrics) if row.metrics is not None and row.status == "ready" else None,
        created_at=row.created_at, updated_at=row.updated_at,
        activate=_requested_activation(row.metrics),
    )


def _requested_activation(metrics: dict[str, Any] | None) -> Activation:
    """The activation asked for when the model was queued: kept in its metrics JSON
    (``activation.requested``), which the training job's record carries on."""
    requested = ((metrics or {}).get("activation") or {}).get("requested")
    return cast(Activation, requested) if requested in ACTIVATIONS else "if_none"


def _select_models():
    return select(Model).execution_options(populate_existing=True)


# --- models -----------------------------------------------------------------------------------


def add_model(s: Session, site_id: int, spec: ModelSpec) -> ModelInfo:
    """A queued training job for ``spec``."""
    row = Model(
        site_id=site_id, algorithm=spec.algorithm, params=dict(spec.params), use_heading=spec.use_heading,
        kinds=list(spec.kinds), include_crowd=spec.include_crowd, status="queued",
        metrics={"activation": {"requested": spec.activate}},
    )
    s.add(row)
    s.flush()
    return _info(row)


def get_model(s: Session, site_id: int, model_id: int) -> ModelInfo | None:
    row = s.scalar(_select_models().where(Model.site_id == site_id, Model.id == model_id))
    return None if row is None else _info(row)


def list_models(s: Session, site_id: int) -> list[ModelInfo]:
    return [_info(row) for row in s.scalars(_select_models().where(Model.site_id == site_id).order_by(Model.id))]


def model_site(s: Session, model_id: int) -> int | None:
    """The site a model belongs to (None: no such model)."""
    return s.scalar(select(Model.site_id).where(Model.id == model_id))


def active_model(s: Session, site_id: int) -> ModelInfo | None:
    row = s.scalar(_select_models().where(Model.site_id == site_id, Model.active.is_(True)))
    return None if row is None else _info(row)


def has_active_model(s: Session, site_id: int) -> bool:
    return bool(s.scalar(select(func.count()).select_from(Model).where(Model.site_id == site_id, Model.active)))


def activate_model(s: Session, site_id: int, model_id: int) -> None:
    """Make ``model_id`` the site's only active model. Readers see the old or the new one,
    never none: both statements commit together."""
    s.execute(update(Model).where(Model.site_id == site_id, Model.active, Model.id != model_id).values(active=False))
    s.execute(update(Model).where(Model.id == model_id).values(active=True))
    touch_site(s, site_id)


# --- the serving model (Core, statements built once: every locate asks) -----------------------------

_SERVING = (
    select(Model.id, Model.algorithm, Model.status, ModelArtifact.sha256)
    .outerjoin(ModelArtifact, ModelArtifact.model_id == Model.id)
    .where(Model.site_id == bindparam("site_id"))
)
#: on the driver's cursor (``_direct``): ``locate`` asks for its serving model on every request
#: its memo cannot answer (PostgreSQL, or any commit since on SQLite, a tracking batch's too)
_SERVING_ACTIVE = DirectStatement(_SERVING.where(Model.active.is_(True)))
_SERVING_CHOSEN = DirectStatement(_SERVING.where(Model.id == bindparam("model_id")))


def serving_model(conn: Connection, site_id: int, model_id: int | None) -> ServingCandidate | None:
    """``model_id`` if it is a model of the site, else (``model_id`` None) the site's active model; ready or not."""
    if model_id is None:
        row = _SERVING_ACTIVE.first(conn, {"site_id": site_id})
    else:
        row = _SERVING_CHOSEN.first(conn, {"site_id": site_id, "model_id": model_id})
    return None if row is None else ServingCandidate(row[0], row[1], cast(ModelStatus, row[2]), row[3])


def survey_grids(s: Session, model_id: int) -> dict[tuple[int, int], float]:
    """The grid direction (degrees) of each floor the model's survey showed one on, by (building,
    floor): its ``metrics.survey_grid`` (none for a model trained before it was measured)."""
    metrics = s.scalar(select(Model.metrics).where(Model.id == model_id)) or {}
    return {(int(g["building"]), int(g["floor"])): float(g["deg"]) for g in metrics.get("survey_grid") or []}


def model_artifact(s: Session, model_id: int) -> Artifact | None:
    row = s.execute(
        select(ModelArtifact.sha256, ModelArtifact.blob).where(ModelArtifact.model_id == model_id)
    ).first()
    return None if row is None else Artifact(model_id, row.sha256, bytes(row.blob))


# --- training jobs ----------------------------------------------------------------------------


def claim_next_model(s: Session, stale_before: datetime) -> int | None:
    """Take the oldest queued job (or one whose worker died: claimed before ``stale_before``)
    with a compare-and-set, so two workers never train the same model."""
    claimable = (Model.status == "queued") | ((Model.status == "training") & (Model.claimed_at < stale_before))
    candidates = s.scalars(select(Model.id).where(claimable).order_by(Model.id).limit(5)).all()
    for model_id in candidates:
        taken = s.execute(
            update(Model)
            .where(Model.id == model_id, claimable)
            .values(status="training", claimed_at=datetime.now(UTC), error=None)
        )
        if changed(taken) == 1:
            return model_id
    return None


def training_job(s: Session, model_id: int) -> ModelInfo | None:
    row = s.scalar(_select_models().where(Model.id == model_id))
    return None if row is None else _info(row)


def finish_training(
    s: Session, model_id: int, blob: bytes, sha256: str, trained_on: int, metrics: dict[str, Any] | None
) -> bool:
    """Store the artifact and mark the model ready: a compare-and-set from ``training`` (False, and
    nothing stored, when the model is no longer in training: deleted, failed, requeued or already done)."""
    done = s.execute(
        update(Model)
        .where(Model.id == model_id, Model.status == "training")
        .values(status="ready", trained_on=trained_on, metrics=metrics, error=None)
    )
    if changed(done) != 1:
        return False
    s.add(ModelArtifact(model_id=model_id, sha256=sha256, blob=blob))
    s.flush()
    return True


def heartbeat(s: Session, model_id: int) -> bool:
    """Renew the claim of a job in training (its worker is alive); False if it is no longer in training."""
    return changed(
        s.execute(update(Model).where(Model.id == model_id, Model.status == "training").values(claimed_at=datetime.now(UTC)))
    ) == 1


def requeue_model(s: Session, model_id: int) -> bool:
    """Hand a job in training back to the queue (its worker is stopping); only from ``training``."""
    return changed(s.execute(update(Model).where(Model.id == model_id, Model.status == "training").values(status="queued"))) == 1


def fail_training(s: Session, model_id: int, error: str) -> bool:
    """Mark a job in training failed; a compare-and-set from ``training`` (a ready model stays ready)."""
    failed = s.execute(
        update(Model).where(Model.id == model_id, Model.status == "training").values(status="failed", error=error[:2000])
    )
    return changed(failed) == 1
