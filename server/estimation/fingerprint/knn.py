"""K nearest neighbours in RSS space (over individual fingerprints).

Floor first: the ``floor_k`` nearest fingerprints vote (weighted) for a
(building, floor); then the ``k`` nearest fingerprints *of that floor* give the
posterior over reference points (weights uniform or 1/distance).
"""

from __future__ import annotations

import numpy as np

from .base import FingerprintModel, TrainingData
from .distance import SquaredDistance, row_sums, smallest_columns

WEIGHTS = ("uniform", "distance")


class KNNModel(FingerprintModel):
    """k: neighbours for the position (default 3); weights: "distance" (1/d) or
    "uniform"; floor_k: neighbours that vote for the floor (None = max(k, 10))."""

    name = "knn"

    def __init__(self, k: int = 3, weights: str = "distance", floor_k: int | None = None, **common):
        super().__init__(**common)
        if weights not in WEIGHTS:
            raise ValueError(f"weights must be one of {WEIGHTS}")
        self.k = int(k)
        if self.k < 1 or (floor_k is not None and int(floor_k) < 1):
            raise ValueError("k and floor_k must be at least 1")
        self.weights = weights
        self.floor_k = floor_k

    def _fit(self, X, H, data: TrainingData) -> None:
        self.dist_ = SquaredDistance(X, H, self.heading_weight_)
        self.row_rp_ = data.rp.row_rp
        self.row_group_ = data.row_group

    def _weights(self, d2: np.ndarray) -> np.ndarray:
        if self.weights == "uniform":
            return np.where(np.isfinite(d2), 1.0, 0.0)
        return np.where(np.isfinite(d2), 1.0 / (np.sqrt(d2) + 1e-6), 0.0)

    def _log_scores(self, Q, Hq, mask):
        d2 = self.dist_(Q, Hq)
        if mask is not None:
            d2 = np.where(mask[:, self.row_rp_], d2, np.inf)
        rows = np.arange(len(d2))[:, None]
        n_groups = len(self.group_floor_)
        # with a floor classifier, ``_predict``'s mask holds one (building, floor) per query: a
        # vote among its points would only pick that group again
        if n_groups > 1 and (mask is None or getattr(self, "floor_clf_", None) is None):
            fk = self.floor_k if self.floor_k is not None else max(self.k, 10)
            idx = smallest_columns(d2, fk)
            w = self._weights(d2[rows, idx])
            g = np.argmax(row_sums(self.row_group_[idx], w, n_groups), axis=1)
            d2 = np.where(self.row_group_[None, :] == g[:, None], d2, np.inf)
        idx = smallest_columns(d2, self.k)
        w = self._weights(d2[rows, idx])
        scores = row_sums(self.row_rp_[idx], w, len(self.rp_xy_))
        with np.errstate(divide="ignore"):
            return np.log(scores)
