"""Fingerprint algorithms by name (the ``algorithm`` field of API.md's Model)."""

from __future__ import annotations

from .base import FingerprintModel
from .kde import KDEModel
from .knn import KNNModel
from .nbc import NBCModel
from .propagation import PropagationModel
from .radiomap import RadioMapModel
from .svm import SVMModel
from .tkbe import TKBEModel
from .wknn import WKNNModel

ALGORITHMS: dict[str, type[FingerprintModel]] = {
    "nbc": NBCModel,
    "knn": KNNModel,
    "svm": SVMModel,
    "kde": KDEModel,
    "tkbe": TKBEModel,
    "propagation": PropagationModel,
    "wknn": WKNNModel,
    "rmap": RadioMapModel,
}


def make_model(algorithm: str, params: dict | None = None, *, use_heading: bool = False,
               kinds: list[str] | None = None) -> FingerprintModel:
    """An unfitted model: ``make_model("knn", {"k": 5}, use_heading=True, kinds=["wifi"])``.
    Raises ValueError for an unknown algorithm or parameter."""
    try:
        cls = ALGORITHMS[algorithm]
    except KeyError:
        raise ValueError(f"unknown algorithm {algorithm!r}; known: {sorted(ALGORITHMS)}") from None
    params = dict(params or {})
    allowed = set(cls._param_names())
    bad = set(params) - allowed
    if bad:
        raise ValueError(f"unknown parameters for {algorithm}: {sorted(bad)}; allowed: {sorted(allowed)}")
    params.setdefault("use_heading", use_heading)
    if kinds is not None:
        params.setdefault("kinds", kinds)
    return cls(**params)
