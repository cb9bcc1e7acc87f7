"""Locate: the site's active (or a chosen) model answers one scan.

Trained models are loaded once per process into a small LRU cache keyed by the
artifact's SHA-256 (content-addressed: a deleted model whose id is reused on SQLite can
never answer for its successor, and nothing needs invalidating); a query only asks the
database which model serves the site, never re-reads an artifact. On SQLite it does not
even ask while nothing at all has been committed to the database since it last asked
(``ServingMemo``): that question cost more CPU than the rest of the service layer.
"""

from __future__ import annotations

import math
import sqlite3
import threading
from collections.abc import Mapping
from urllib.parse import quote

from sqlalchemy import make_url

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


class ServingMemo:
    """The serving model of each (site, model asked), remembered while the SQLite database at
    ``path`` has had no commit at all since it was read.

    ``PRAGMA data_version`` on a connection of this memo's own (which never writes) changes
    whenever any other connection, of this process or another, commits anything; it is read
    before the database is asked, so an answer is never older than the version it is kept
    under. Any commit (a model activated, trained or deleted, but also a session's batch)
    forgets everything. The check costs a few µs where the query cost ≈ 100 µs of CPU per
    locate (SQLAlchemy's path through a pooled connection, its caches cold after the model's
    work). ``path`` None (PostgreSQL, an in-memory database): nothing is remembered."""

    def __init__(self, path: str | None, size: int = 1024):
        self._path = path
        self._size = size
        self._conn: sqlite3.Connection | None = None
        self._lock = threading.Lock()
        self._version: int | None = None
        self._serving: dict[tuple[int, int | None], ServingModel] = {}

    @classmethod
    def for_database(cls, db: Database) -> ServingMemo:
        path = make_url(db.url).database if db.embedded else None
        usable = path and path != ":memory:" and not path.startswith("file:")
        return cls(path if usable else None)

    def version(self) -> int | None:
        """The database's data version now; None when it cannot be told (nothing is remembered)."""
        if self._path is None:
            return None
        with self._lock:
            try:
                if self._conn is None:
                    self._conn = sqlite3.connect(f"file:{quote(self._path)}?mode=rw", uri=True,  # never creates one
                                                 check_same_thread=False, isolation_level=None, timeout=1.0)
                version = int(self._conn.execute("PRAGMA data_version").fetchone()[0])
            except sqlite3.Error:
                return None
            if version != self._version:
                self._serving.clear()
                self._version = version
            return version

    def get(self, version: int, key: tuple[int, int | None]) -> ServingModel | None:
        with self._lock:
            return self._serving.get(key) if version == self._version else None

    def put(self, version: int, key: tuple[int, int | None], serving: ServingModel) -> None:
        """Keep ``serving``, read after ``version`` was: only while that version is still the latest seen."""
        with self._lock:
            if version == self._version:
                if len(self._serving) >= self._size:
                    self._serving.clear()
                self._serving[key] = serving


class Positioning:
    def __init__(self, db: Database, cache: ModelCache):
        self._db = db
        self.cache = cache
        self._memo = ServingMemo.for_database(db)

    def serving_model(self, site_id: int, model_id: int | None = None) -> ServingModel:
        """The model that answers for the site: ``model_id``, else the site's active model.
        ``NotFound`` (no such site or model) or ``Conflict`` (no model, or not ready) when none can."""
        version = self._memo.version()  # before the database is asked (``ServingMemo``)
        if version is not None:
            remembered = self._memo.get(version, (site_id, model_id))
            if remembered is not None:
                return remembered
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
        if version is not None:
            self._memo.put(version, (site_id, model_id), serving)
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
        """A fix for one scan; ``near``/``radius_m`` restrict candidates around a previous estimate
        (a tracking session's search circle; a model trained on crowd fingerprints answers anywhere).
        ``serving`` names the model when the caller already knows it (else the database is asked)."""
        serving = serving or self.serving_model(site_id, model_id)
        model = self.cache.get(serving.model_id, serving.sha256)
        try:
            fix = model.locate(rss, heading_deg, near=near, radius_m=radius_m)
        except UnknownTransmittersError:
            raise unknown_scan(serving) from None
        return Located(fix, serving.model_id, serving.algorithm)

    def locate_answer(
        self, site_id: int, rss: Mapping[str, float], heading_deg: float | None = None, model_id: int | None = None,
    ) -> Located:
        """``locate`` for a phone asking where it is: the fix and whether the scan resembles anything surveyed
        (a ``wknn`` model measures both in one distance pass)."""
        serving = self.serving_model(site_id, model_id)
        model = self.cache.get(serving.model_id, serving.sha256)
        if not isinstance(model, WKNNModel) or (threshold := coverage_threshold(model)) is None:
            return self.locate(site_id, rss, heading_deg, serving=serving)
        try:
            fix, nearest = model.locate_covered(rss, heading_deg)
        except UnknownTransmittersError:
            raise unknown_scan(serving) from None
        # a distance is ≥ 0; a scan equal to a stored fingerprint can come out at −1e-8 from rounding
        return Located(fix, serving.model_id, serving.algorithm, coverage=Coverage(ratio=max(nearest, 0.0) / threshold))


def coverage_threshold(model: WKNNModel) -> float | None:
    """The model's coverage threshold: finite and positive from its internal cross-validation, else None
    (the model then cannot tell whether a scan is covered)."""
    threshold = float(getattr(model, "coverage_threshold_", math.inf))
    return threshold if math.isfinite(threshold) and threshold > 0 else None


def unknown_scan(serving: ServingModel) -> InvalidField:
    """The 422 for a scan none of whose transmitters the serving model knows."""
    return InvalidField("rss", f"no transmitter in the scan is known to model {serving.model_id}")
