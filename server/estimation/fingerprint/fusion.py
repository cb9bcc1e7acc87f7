"""Cold start / initial fix: weighted fusion of a fingerprint estimate and a
least-squares multilateration estimate (DESIGN.md).

Weights ``w_i = exp(−d_i) / Σ_j exp(−d_j)``. ``d_i`` is each estimate's badness in
dimensionless units; by default its RMS spread per axis, ``sqrt(trace(Σ_i)/2)``,
divided by ``scale_m`` — so an estimate 1·scale_m less spread out gets e times the
weight. Pass ``distances`` to use another measure (e.g. an RSS-space residual).
The fused fix is the mixture's first two moments, so disagreement between the two
estimates widens its covariance.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from server.estimation.types import Fix


def exp_weights(distances: Sequence[float]) -> np.ndarray:
    d = np.asarray(distances, dtype=float)
    w = np.exp(-(d - d.min()))
    return w / w.sum()


def spread_distance(fix: Fix, scale_m: float = 1.0) -> float:
    return float(np.sqrt(np.trace(np.asarray(fix.covariance)) / 2.0)) / scale_m


def fuse_fixes(fixes: Sequence[Fix], distances: Sequence[float] | None = None, scale_m: float = 1.0) -> Fix:
    """Fuse several estimates of the same position with weights exp(−d) normalised.
    The building and floor are those of the heaviest estimate; candidates and reference point too."""
    fixes = [f for f in fixes if f is not None]
    if not fixes:
        raise ValueError("nothing to fuse")
    if distances is None:
        distances = [spread_distance(f, scale_m) for f in fixes]
    w = exp_weights(distances)
    means = np.array([f.mean for f in fixes])
    mean = w @ means
    cov = np.zeros((2, 2))
    for wi, f, mu in zip(w, fixes, means, strict=True):
        d = mu - mean
        cov += wi * (np.asarray(f.covariance, dtype=float) + np.outer(d, d))
    top = fixes[int(np.argmax(w))]
    return Fix(x=float(mean[0]), y=float(mean[1]), floor=top.floor, covariance=cov,
               reference_point=top.reference_point, candidates=list(top.candidates), building=top.building)


def cold_start_fix(fingerprint_fix: Fix | None, multilateration_fix: Fix | None,
                   d_fingerprint: float | None = None, d_multilateration: float | None = None,
                   scale_m: float = 1.0) -> Fix:
    """The initial fix of a session from a fingerprint estimate and a multilateration
    estimate (either may be None). If their floors (or buildings) differ, the fingerprint's
    is kept and the other estimate is dropped (never mix floors)."""
    if fingerprint_fix is None or multilateration_fix is None:
        only = fingerprint_fix or multilateration_fix
        if only is None:
            raise ValueError("nothing to fuse")
        return only
    if (fingerprint_fix.building, fingerprint_fix.floor) != (multilateration_fix.building, multilateration_fix.floor):
        return fingerprint_fix
    d = None
    if d_fingerprint is not None or d_multilateration is not None:
        d = [
            spread_distance(fingerprint_fix, scale_m) if d_fingerprint is None else d_fingerprint,
            spread_distance(multilateration_fix, scale_m) if d_multilateration is None else d_multilateration,
        ]
    return fuse_fixes([fingerprint_fix, multilateration_fix], d, scale_m)
