"""Locate: the site's active (or a chosen) model answers one scan.

Trained models are loaded once per process into a small LRU cache keyed by the
artifact's SHA-256 (content-addressed: a deleted model whose id is reused on SQLite can
never answer for its successor, and nothing needs invalidating); a query only asks the
database which model serves the site, never re-reads an artifact.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping
from dataclasses import dataclass

from server import repositories as repo
from server.db import Database
from server.errors import Conflict, Invalid, NotFound
from server.estimation.fingerprint import (
    ArtifactError,
    FingerprintModel,
    UnknownTransmittersError,
    checksum,
    from_bytes,
)
from server.estimation.types import Fix
from server.inline import WouldBlock, on_event_loop
from server.services.lru import Lru

#: (model id, algorithm, artifact SHA-256) of a ready model
ServingModel = tuple[int, str, str]


def ready_model(found: tuple | None) -> ServingModel | None:
    """A row of ``repositories.serving_model`` as the model that serves, if it is ready to."""
    if found is None:
        return None
    model_id, algorithm, status, sha256 = found
    return (model_id, algorithm, sha256) if status == "ready" and sha256 is not None else None


@dataclass(frozen=True)
class Located:
    fix: Fix
    model_id: int
    algorithm: str


class ModelCache:
    """Loaded models by artifact SHA-256, least recently used dropped first; loads are checksum-verified.
    Work on the event loop gets ``WouldBlock`` instead of a load (see ``server.inline``)."""

    def __init__(self, db: Database, size: int = 8):
        self._db = db
        self._models: Lru[str, FingerprintModel] = Lru(size)
        self._loading = threading.Lock()  # one load at a time: two requests never load one model twice
        self.loads = 0

    def get(self, model_id: int, sha256: str) -> FingerprintModel:
        model = self._models.get(sha256)
        if model is not None:
            return model
        if on_event_loop.get():
            raise WouldBlock(f"model {model_id} is not loaded in this process yet")
        with self._loading:
            model = self._models.get(sha256)
            if model is not None:
                return model
            with self._db.transaction() as s:
                artifact = repo.model_artifact(s, model_id)
                if artifact is None or artifact.sha256 != sha256:
                    raise Conflict(f"model {model_id} changed while it was being loaded; retry")
                blob = bytes(artifact.blob)
            if checksum(blob) != sha256:
                raise ArtifactError(f"model {model_id}: artifact does not match its recorded SHA-256")
            model = from_bytes(blob)
            self.loads += 1
            self._models.put(sha256, model)
            return model


class Positioning:
    def __init__(self, db: Database, cache: ModelCache):
        self._db = db
        self.cache = cache

    def serving_model(self, site_id: int, model_id: int | None = None) -> ServingModel:
        """(id, algorithm, artifact SHA-256) of the model that answers for the site: 404/409 when there is none."""
        with self._db.read() as conn:
            found = repo.serving_model(conn, site_id, model_id)
        if found is None:
            with self._db.transaction() as s:
                if repo.get_site(s, site_id) is None:
                    raise NotFound(f"site {site_id} does not exist")
                if model_id is not None:
                    raise NotFound(f"model {model_id} does not exist on site {site_id}")
                raise Conflict(f"site {site_id} has no ready model: train one with POST /api/v1/sites/{site_id}/models")
        serving = ready_model(found)
        if serving is None:
            raise Conflict(f"model {found[0]} is {found[2]}, not ready")
        return serving

    def locate(
        self,
        site_id: int,
        rss: Mapping[str, float],
        heading_deg: float | None = None,
        model_id: int | None = None,
        near: Fix | tuple[float, float] | None = None,
        radius_m: float | None = None,
        serving: ServingModel | None = None,
    ) -> Located:
        """A fix for one scan; ``near``/``radius_m`` restrict candidates around a previous estimate.
        ``serving`` names the model when the caller already knows it (else the database is asked)."""
        found_id, algorithm, sha256 = serving or self.serving_model(site_id, model_id)
        model = self.cache.get(found_id, sha256)
        try:
            fix = model.locate(rss, heading_deg, near=near, radius_m=radius_m)
        except UnknownTransmittersError:
            raise Invalid(
                [{"loc": ["body", "rss"], "field": "rss",
                  "msg": f"no transmitter in the scan is known to model {found_id}"}]
            ) from None
        return Located(fix, found_id, algorithm)
