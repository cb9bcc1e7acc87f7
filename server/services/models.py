"""Fingerprint models of a site: queue a training job, list, activate."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from sqlalchemy.orm import Session

from server.db import Database
from server.domain import ModelInfo, ModelSpec
from server.errors import Conflict, InvalidField, NotFound
from server.estimation.fingerprint.metrics import PointError
from server.services.training import build_model, held_out_points
from server.store import models as store
from server.store import sites as site_store


class ModelService:
    """``on_queued`` is called after a job is queued (it wakes this process's training worker)."""

    def __init__(self, db: Database, on_queued: Callable[[], None] | None = None):
        self._db = db
        self._on_queued = on_queued

    def queue(self, site_id: int, spec: ModelSpec) -> ModelInfo:
        """Check the algorithm and its parameters now, train later in the background."""
        spec = dataclasses.replace(spec, kinds=tuple(sorted(set(spec.kinds))))
        try:
            build_model(spec.algorithm, dict(spec.params), spec.use_heading, list(spec.kinds), transmitters=[])
        except ValueError as exc:
            raise InvalidField("algorithm" if "algorithm" in str(exc) else "params", str(exc)) from None
        except TypeError as exc:
            raise InvalidField("params", f"invalid parameter value: {exc}") from None
        with self._db.transaction() as s:
            _existing_site(s, site_id)
            model = store.add_model(s, site_id, spec)
        if self._on_queued is not None:
            self._on_queued()
        return model

    def list_models(self, site_id: int) -> list[ModelInfo]:
        with self._db.transaction() as s:
            _existing_site(s, site_id)
            return store.list_models(s, site_id)

    def get(self, site_id: int, model_id: int) -> ModelInfo:
        with self._db.transaction() as s:
            return _existing(s, site_id, model_id)

    def held_out_errors(self, site_id: int, model_id: int) -> list[PointError]:
        """Each held-out reference point's mean error, as the model's training measured it
        (where the radio map is weak); 409 until the model is ready."""
        with self._db.transaction() as s:
            model = _existing(s, site_id, model_id)
        if model.status != "ready":
            raise Conflict(f"model {model_id} is {model.status}; held-out errors exist once it is ready")
        return held_out_points(model.metrics)

    def activate(self, site_id: int, model_id: int) -> ModelInfo:
        """Swap the site's active model in one transaction; only a ready model can serve."""
        with self._db.transaction() as s:
            model = _existing(s, site_id, model_id)
            if model.status != "ready":
                raise Conflict(f"model {model_id} is {model.status}; only a ready model can be activated")
            store.activate_model(s, site_id, model_id)
            return _existing(s, site_id, model_id)


def _existing_site(s: Session, site_id: int) -> None:
    if not site_store.site_exists(s, site_id):
        raise NotFound(f"site {site_id} does not exist")


def _existing(s: Session, site_id: int, model_id: int) -> ModelInfo:
    model = store.get_model(s, site_id, model_id)
    if model is None:
        _existing_site(s, site_id)
        raise NotFound(f"model {model_id} does not exist on site {site_id}")
    return model
