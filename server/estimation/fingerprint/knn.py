"""K nearest neighbours over individual fingerprints, k fixed (DESIGN: k = 3, weighted variant).

The same search as ``wknn`` (wknn.py: building → floor → position, Sørensen distance over
the exponential RSS representation, the per-query RSS offset estimate, cleaning, the
calibrated covariance), with ``k`` given rather than chosen by cross-validation and the
neighbours weighted by 1/d ("distance", default) or equally ("uniform").

Why not a KNN of its own: the previous ``knn`` (squared Euclidean distance over the floor
representation, an SVC picking the floor) was no better than a bare scikit-learn KNN on
UJIIndoorLoc's held-out users (docs/fingerprint-results.md, "knn rebuilt on wknn's
search"): its representation and distance, not its k, were what held it back.

Artifacts of the previous ``knn`` (``dist_`` in their state) are refused with
ArtifactError; migration 0010 re-queues such models so the server retrains them.
"""

from __future__ import annotations

from .artifact import ArtifactError
from .wknn import WKNNModel

WEIGHTS = ("uniform", "distance")


class KNNModel(WKNNModel):
    """k: neighbours for the position (default 3); weights: "distance" (1/d) or "uniform";
    floor_k: neighbours that vote for the floor (None = max(k, 10)). Every ``wknn``
    parameter but ``k_grid`` applies too (``k_grid`` is ignored: k is not chosen)."""

    name = "knn"

    def __init__(self, k: int = 3, weights: str = "distance", floor_k: int | None = None, **common):
        if weights not in WEIGHTS:
            raise ValueError(f"weights must be one of {WEIGHTS}")
        if k is None:  # (wknn's None, k chosen by cross-validation, is not knn's)
            raise ValueError("k must be at least 1")
        # wknn checks that k and floor_k are at least 1
        super().__init__(k=k, floor_k=max(int(k), 10) if floor_k is None else floor_k, **common)
        self.weights = weights

    def __setstate__(self, state: dict) -> None:
        if "dist_" in state:
            raise ArtifactError("artifact of the previous knn (before it was built on wknn's search): retrain the model")
        super().__setstate__(state)
