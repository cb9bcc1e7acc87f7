"""Locate: the site's active (or a chosen) model answers one scan.

Trained models are loaded once per process into a small LRU cache keyed by the
artifact's SHA-256 (content-addressed: a deleted model whose id is reused on SQLite can
never answer for its successor, and nothing needs invalidating); a query only asks the
database which model serves the site, never re-reads an artifact.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping

from server.db import Database
from server.domain import Coverage, Located, ServingModel
from server.errors import Conflict, InvalidField, NoReadyModel, NotFound
from server.estimation.fingerprint import (
    ArtifactError,
    FingerprintModel,
    UnknownTransmittersError,
    WKNNModel,
    checksum,
    from_bytes,
)
from server.estimation.types import Fix
from server.inline import WouldBlock, on_event_loop
from server.services.lru import Lru
from server.store import models as store
from server.store import sites as site_store


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
                artifact = store.model_artifact(s, model_id)
            if artifact is None or artifact.sha256 != sha256:
                raise Conflict(f"model {model_id} changed while it was being loaded; retry")
            try:
                if checksum(artifact.blob) != sha256:
                    raise ArtifactError("the artifact does not match its recorded SHA-256")
                model = from_bytes(artifact.blob)
            except ArtifactError as exc:  # tampered, or stored by another library version
                raise Conflict(f"model {model_id} cannot be loaded ({exc}); train a new model") from None
            self.loads += 1
            self._models.put(sha256, model)
            return model


class Positioning:
    def __init__(self, db: Database, cache: ModelCache):
        self._db = db
        self.cache = cache

    def serving_model(self, site_id: int, model_id: int | None = None) -> ServingModel:
        """The model that answers for the site: ``model_id``, else the site's active model.
        ``NotFound`` (no such site or model) or ``Conflict`` (no model, or not ready) when none can."""
        with self._db.read() as conn:
            found = store.serving_model(conn, site_id, model_id)
        if found is None:
            with self._db.transaction() as s:
                if not site_store.site_exists(s, site_id):
                    raise NotFound(f"site {site_id} does not exist")
            if model_id is not None:
                raise NotFound(f"model {model_id} does not exist on site {site_id}")
            raise NoReadyModel(site_id)
        serving = found.ready()
        if serving is None:
            raise Conflict(f"model {found.model_id} is {found.status}, not ready")
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
        serving = serving or self.serving_model(site_id, model_id)
        model = self.cache.get(serving.model_id, serving.sha256)
        try:
            fix = model.locate(rss, heading_deg, near=near, radius_m=radius_m)
        except UnknownTransmittersError:
            raise InvalidField("rss", f"no transmitter in the scan is known to model {serving.model_id}") from None
        return Located(fix, serving.model_id, serving.algorithm)

    def locate_answer(
        self, site_id: int, rss: Mapping[str, float], heading_deg: float | None = None, model_id: int | None = None,
    ) -> Located:
        """``locate`` for a phone asking where it is: the fix and whether the scan resembles anything surveyed
        (a ``wknn`` model measures both in one distance pass)."""
        serving = self.serving_model(site_id, model_id)
        model = self.cache.get(serving.model_id, serving.sha256)
        threshold = coverage_threshold(model)
        if threshold is None or not isinstance(model, WKNNModel):
            return self.locate(site_id, rss, heading_deg, serving=serving)
        try:
            fix, nearest = model.locate_covered(rss, heading_deg)
        except UnknownTransmittersError:
            raise InvalidField("rss", f"no transmitter in the scan is known to model {serving.model_id}") from None
        return Located(fix, serving.model_id, serving.algorithm, coverage=Coverage(ratio=nearest / threshold))


def coverage_threshold(model: FingerprintModel) -> float | None:
    """The coverage threshold of a model that measures coverage (``wknn``, with a finite threshold from its
    internal cross-validation); None for the others."""
    threshold = float(getattr(model, "coverage_threshold_", math.inf))
    return threshold if isinstance(model, WKNNModel) and math.isfinite(threshold) and threshold > 0 else None
