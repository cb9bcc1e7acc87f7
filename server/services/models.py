"""Fingerprint models of a site: queue a training job, list, activate."""

from __future__ import annotations

from collections.abc import Sequence

from server import repositories as repo
from server.db import Database
from server.errors import Conflict, Invalid, NotFound
from server.schemas import ModelIn
from server.services.training import build_model
from server.tables import Model


def _field_error(field: str, msg: str) -> Invalid:
    return Invalid([{"loc": ["body", field], "field": field, "msg": msg}])


def queue_model(db: Database, site_id: int, body: ModelIn) -> Model:
    """Check the algorithm and its parameters now (422), train later in the background."""
    try:
        build_model(body.algorithm, body.params, body.use_heading, body.kinds, transmitters=[])
    except ValueError as exc:
        raise _field_error("algorithm" if "algorithm" in str(exc) else "params", str(exc)) from None
    except TypeError as exc:
        raise _field_error("params", f"invalid parameter value: {exc}") from None
    with db.transaction() as s:
        if repo.get_site(s, site_id) is None:
            raise NotFound(f"site {site_id} does not exist")
        kinds = sorted(set(body.kinds)) if body.kinds else []
        return repo.add_model(s, site_id, body.algorithm, body.params, body.use_heading, kinds, body.include_crowd)


def list_models(db: Database, site_id: int) -> Sequence[Model]:
    with db.transaction() as s:
        if repo.get_site(s, site_id) is None:
            raise NotFound(f"site {site_id} does not exist")
        return repo.list_models(s, site_id)


def get_model(db: Database, site_id: int, model_id: int) -> Model:
    with db.transaction() as s:
        return _existing(s, site_id, model_id)


def activate(db: Database, site_id: int, model_id: int) -> Model:
    """Swap the site's active model in one transaction; only a ready model can serve."""
    with db.transaction() as s:
        model = _existing(s, site_id, model_id)
        if model.status != "ready":
            raise Conflict(f"model {model_id} is {model.status}; only a ready model can be activated")
        repo.activate_model(s, site_id, model_id)
        s.refresh(model)
        return model


def _existing(s, site_id: int, model_id: int) -> Model:
    model = repo.get_model(s, site_id, model_id)
    if model is None:
        if repo.get_site(s, site_id) is None:
            raise NotFound(f"site {site_id} does not exist")
        raise NotFound(f"model {model_id} does not exist on site {site_id}")
    return model
