"""The log-distance radio model and what is derived from it, in one place.

``RSS = R0 − 10·γ·log10(d)`` (d in metres, R0 = RSS at 1 m, γ = path-loss exponent).
Inverting gives the range ``d = 10^((R0 − RSS) / (10·γ))``; an RSS error of σ dBm maps,
to first order, to a range error ``σ_d = d · ln(10) · σ / (10·γ)`` (it grows with the
range, which is why beacon ranges are only used close to the beacon). Ranges to anchors
at known positions give a position by least-squares multilateration.

Used by the propagation fingerprint model (fit, ranges, multilateration), by tracking
sessions (beacon ranges, cold-start fixes) and by the test site generators.
"""

from __future__ import annotations

import math
from typing import TypeVar

import numpy as np
from scipy.optimize import least_squares

#: a float, or an array of them (the formulas work elementwise on either)
FloatOrArray = TypeVar("FloatOrArray", float, np.ndarray)


def rss_at(distance_m: FloatOrArray, r0_dbm: FloatOrArray | float, gamma: FloatOrArray | float) -> FloatOrArray:
    """RSS (dBm) the model predicts at ``distance_m`` (no clipping: pass d ≥ 1 m)."""
    return r0_dbm - 10.0 * gamma * np.log10(distance_m)


def range_from_rss(rss_dbm: FloatOrArray, r0_dbm: FloatOrArray | float, gamma: FloatOrArray | float) -> FloatOrArray:
    """Distance in metres at which the model predicts ``rss_dbm``."""
    if np.any(np.asarray(gamma) <= 0):
        raise ValueError("path-loss exponent gamma must be positive")
    return 10.0 ** ((r0_dbm - rss_dbm) / (10.0 * gamma))


def range_std_from_rss(range_m: float, rss_std_db: float, gamma: float) -> float:
    """First-order standard deviation of the range for an RSS noise of ``rss_std_db``."""
    if gamma <= 0:
        raise ValueError("path-loss exponent gamma must be positive")
    return range_m * math.log(10.0) * rss_std_db / (10.0 * gamma)


def range_and_std(rss_dbm: float, r0_dbm: float, gamma: float, rss_std_db: float = 4.0) -> tuple[float, float]:
    """(range_m, range_std_m) for one RSS reading."""
    d = float(range_from_rss(float(rss_dbm), r0_dbm, gamma))
    return d, range_std_from_rss(d, rss_std_db, gamma)


def fit_path_loss(distance_m, rss_dbm, min_distance_m: float = 1.0,
                  gamma_bounds: tuple[float, float] = (1.0, 6.0)) -> tuple[float, float]:
    """Least-squares (R0, γ) from readings at known distances. Needs ≥ 2 distinct
    distances; γ is clipped to ``gamma_bounds`` (R0 refitted with γ fixed)."""
    d = np.maximum(np.asarray(distance_m, dtype=float), min_distance_m)
    r = np.asarray(rss_dbm, dtype=float)
    ok = np.isfinite(d) & np.isfinite(r)
    d, r = d[ok], r[ok]
    L = -10.0 * np.log10(d)
    if len(r) < 2 or np.ptp(L) < 1e-6:
        raise ValueError("need readings at two or more distinct distances")
    A = np.column_stack([np.ones_like(L), L])
    (r0, g), *_ = np.linalg.lstsq(A, r, rcond=None)
    if not gamma_bounds[0] <= g <= gamma_bounds[1]:
        g = float(np.clip(g, *gamma_bounds))
        r0 = float(np.mean(r - g * L))
    return float(r0), float(g)


def weighted_centroid(anchors_xy: np.ndarray, ranges_m: np.ndarray) -> np.ndarray:
    """Centroid of the anchors weighted by 1/range."""
    w = 1.0 / np.maximum(np.asarray(ranges_m, dtype=float), 0.1)
    return (np.asarray(anchors_xy) * w[:, None]).sum(0) / w.sum()


def multilaterate(anchors_xy: np.ndarray, ranges_m: np.ndarray, x0=None,
                  min_rel_error: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares position from ranges to anchors (relative residuals
    ``(|p − a| − r)/r``, soft-L1). Returns (xy, 2×2 covariance in m²). Fewer than three
    anchors: the weighted centroid with a covariance from the ranges.

    The covariance is s²(JᵀJ)⁻¹ (s the relative range error) taken through JᵀJ's eigenvalues (each at
    least 10⁻¹² of the largest): with the anchors nearly in a line and the position on it, JᵀJ is
    nearly singular, and its plain inverse claimed σ ≈ 10⁸ m across the line and lost the
    well-determined direction's variance to rounding (a fix then looked exact along it)."""
    A = np.asarray(anchors_xy, dtype=float)
    r = np.maximum(np.asarray(ranges_m, dtype=float), 0.5)
    start = weighted_centroid(A, r) if x0 is None else np.asarray(x0, dtype=float)
    if len(A) < 3:
        s = float(np.min(r))
        return start, np.eye(2) * s**2

    def resid(p):
        return (np.hypot(*(p - A).T) - r) / r

    sol = least_squares(resid, start, loss="soft_l1", f_scale=0.3)
    J = sol.jac
    s2 = max(float(np.sum(sol.fun**2)) / max(len(A) - 2, 1), min_rel_error**2)
    lam, V = np.linalg.eigh(J.T @ J)
    cov = s2 * (V / np.maximum(lam, 1e-12 * max(float(lam[-1]), 1e-300))) @ V.T
    if not np.all(np.isfinite(cov)) or np.any(np.diag(cov) <= 0):
        cov = np.eye(2) * (s2 * float(np.mean(r)) ** 2)
    return sol.x, cov
