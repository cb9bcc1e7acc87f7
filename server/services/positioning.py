"""Locate: the site's active (or a chosen) model answers one scan.

Trained models are loaded once per process into a small LRU cache keyed by model id
(ids never change meaning, so no invalidation is needed); a query only asks the
database which model serves the site, never re-reads an artifact.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
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


@dataclass(frozen=True)
class Located:
    fix: Fix
    model_id: int
    algorithm: str


class ModelCache:
    """Loaded models by id, least recently used dropped first; loads are checksum-verified."""

    def __init__(self, db: Database, size: int = 8):
        self._db = db
        self._size = size
        self._models: OrderedDict[int, FingerprintModel] = OrderedDict()
        self._lock = threading.Lock()
        self.loads = 0

    def get(self, model_id: int) -> FingerprintModel:
        with self._lock:
            model = self._models.get(model_id)
            if model is not None:
                self._models.move_to_end(model_id)
                return model
            with self._db.transaction() as s:
                artifact = repo.model_artifact(s, model_id)
                if artifact is None:
                    raise Conflict(f"model {model_id} has no stored artifact")
                blob, sha256 = bytes(artifact.blob), artifact.sha256
            if checksum(blob) != sha256:
                raise ArtifactError(f"model {model_id}: artifact does not match its recorded SHA-256")
            model = from_bytes(blob)
            self.loads += 1
            self._models[model_id] = model
            if len(self._models) > self._size:
                self._models.popitem(last=False)
            return model


class Positioning:
    def __init__(self, db: Database, cache: ModelCache):
        self._db = db
        self.cache = cache

    def serving_model(self, site_id: int, model_id: int | None = None) -> tuple[int, str]:
        """(id, algorithm) of the model that answers for the site: 404/409 when there is none."""
        with self._db.transaction() as s:
            found = repo.serving_model(s, site_id, model_id)
            if found is None:
                if repo.get_site(s, site_id) is None:
                    raise NotFound(f"site {site_id} does not exist")
                if model_id is not None:
                    raise NotFound(f"model {model_id} does not exist on site {site_id}")
                raise Conflict(f"site {site_id} has no ready model: train one with POST /api/v1/sites/{site_id}/models")
        found_id, algorithm, status = found
        if status != "ready":
            raise Conflict(f"model {found_id} is {status}, not ready")
        return found_id, algorithm

    def locate(
        self,
        site_id: int,
        rss: Mapping[str, float],
        heading_deg: float | None = None,
        model_id: int | None = None,
        near: Fix | tuple[float, float] | None = None,
        radius_m: float | None = None,
    ) -> Located:
        """A fix for one scan; ``near``/``radius_m`` restrict candidates around a previous estimate."""
        found_id, algorithm = self.serving_model(site_id, model_id)
        model = self.cache.get(found_id)
        try:
            fix = model.locate(rss, heading_deg, near=near, radius_m=radius_m)
        except UnknownTransmittersError:
            raise Invalid(
                [{"loc": ["body", "rss"], "field": "rss",
                  "msg": f"no transmitter in the scan is known to model {found_id}"}]
            ) from None
        return Located(fix, found_id, algorithm)
