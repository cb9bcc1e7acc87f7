"""Calibrated fix covariances: how a model's covariance C maps to its real errors.

A model's covariance (the posterior spread over reference points plus a floor) is a
shape, not a calibrated error: a tracker that takes it as R needs held-out residuals r
to follow N(0, C). `fit_calibration` fits ``C' = scale·C + floor_m²·I`` on held-out
residuals so the normalised innovation squared ``rᵀC'⁻¹r`` (NIS) is distributed as a
χ² with 2 degrees of freedom (mean 2, median 2 ln 2): for each floor on a grid the
scale that puts the NIS mean at 2 — the mean taken with each NIS clipped at χ²₂'s
99.9 % quantile, so a few gross errors (a wrong floor) count but cannot decide alone —
and of those the pair whose NIS median is closest to 2 ln 2. A scale alone cannot
match both when most held-out scans land on their own reference point (errors near
0) and a few far away; the floor widens small covariances relative to large ones.

Small held-out samples (a site surveyed at 60 points holds out a dozen) cannot tell a
scale from a floor, and the two-parameter fit then swings over orders of magnitude (a
scale of 0.005 or 7 on sites of one simulator family). Below ``TWO_PARAMETERS_FROM``
residuals only the scale is fitted, shrunk towards 1 in log space with the weight of
``SHRINK_N`` residuals (log s ← n/(n + SHRINK_N)·log ŝ): a few residuals move it a
little, many move it all the way. Both chosen on the tune scenarios of
benchmarks/scenario_family.py (tracking error and NEES with the served fixes).

The training step fits it on its held-out sample for every algorithm; every Fix the
model answers then carries ``apply(C)``.

**The walk's share** (``walk_share``, `measure_walk_share`): a fingerprint map's errors are not
independent along a walk — one phone, one body, one stretch of the map's own mistakes — so two
fixes of a walk share part of their error. Where the training step holds out whole groups
(walks or phones, `metrics.group_held_out`) it measures that share from pairs of one group's
held-out rows at least ``WALK_SHARE_MIN_M`` apart (the part that lasts, not the map's local
smoothness): 0.24–0.70 on the four MSFT site-1 fold maps (``benchmarks/fix_correlation.py`` prints
them; the test walks' fixes share 0.42–0.45 beyond 10 m). Every fix then carries it
(``Fix.shared_share``), and an EKF session with ``walk_offset`` 1 (opt-in) estimates the walk's
offset instead of taking each fix's error as new. Splits by reference point cannot see a walk:
None (unknown).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CHI2_2_MEDIAN = 2.0 * np.log(2.0)
#: floors tried (m); 0 = a pure scale
FLOOR_GRID_M = (0.0, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 15.0, 20.0, 30.0)
#: χ²₂'s 99.9 % quantile, where each NIS is clipped for the mean, and that clipped mean
NIS_CLIP = -2.0 * np.log(1e-3)
CLIPPED_MEAN = 2.0 * (1.0 - 1e-3)
#: fewer held-out residuals than this: a shrunk scale only (module docstring)
TWO_PARAMETERS_FROM = 300
SHRINK_N = 30.0
#: the walk's share is measured on pairs of one group's held-out rows at least this far apart (m),
#: on groups with at least WALK_SHARE_MIN_PAIRS such pairs, from at least WALK_SHARE_MIN_GROUPS
#: groups, and kept within [0, WALK_SHARE_MAX] (`measure_walk_share`)
WALK_SHARE_MIN_M = 10.0
WALK_SHARE_MIN_PAIRS = 10
WALK_SHARE_MIN_GROUPS = 5
WALK_SHARE_MAX = 0.9


@dataclass(frozen=True)
class CovarianceCalibration:
    """``C' = scale·C + floor_m²·I``; identity by default (an uncalibrated model). ``walk_share``:
    the share of C' that a walk's fixes have in common (None: not measured)."""

    scale: float = 1.0
    floor_m: float = 0.0
    walk_share: float | None = None

    def apply(self, cov: np.ndarray) -> np.ndarray:
        """(n, 2, 2) covariances, calibrated (a new array)."""
        out = np.asarray(cov, dtype=float) * self.scale
        out[..., 0, 0] += self.floor_m**2
        out[..., 1, 1] += self.floor_m**2
        return out


IDENTITY = CovarianceCalibration()


def nis(residuals: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """rᵀC⁻¹r per row: residuals (n, 2), covariances (n, 2, 2)."""
    r = np.asarray(residuals, dtype=float)
    c = np.asarray(cov, dtype=float)
    a, b, d = c[:, 0, 0], c[:, 0, 1], c[:, 1, 1]
    det = np.maximum(a * d - b * b, 1e-300)
    return (d * r[:, 0] ** 2 - 2 * b * r[:, 0] * r[:, 1] + a * r[:, 1] ** 2) / det


def clipped_mean(values: np.ndarray) -> float:
    """Mean NIS with each value clipped at NIS_CLIP (a calibrated fix: CLIPPED_MEAN ≈ 2)."""
    return float(np.mean(np.minimum(values, NIS_CLIP)))


def _scale_for_mean(r: np.ndarray, cov: np.ndarray, floor_m: float) -> float | None:
    """The scale s with clipped-mean NIS(s·C + floor²I) = CLIPPED_MEAN (bisection on log s;
    NIS falls as s grows); None when the floor alone already makes it too small."""
    def mean(s: float) -> float:
        return clipped_mean(nis(r, CovarianceCalibration(s, floor_m).apply(cov)))

    lo, hi = -14.0, 14.0  # log s
    if mean(np.exp(lo)) < CLIPPED_MEAN:
        return None
    if mean(np.exp(hi)) > CLIPPED_MEAN:
        return float(np.exp(hi))
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        if mean(np.exp(mid)) > CLIPPED_MEAN:
            lo = mid
        else:
            hi = mid
    return float(np.exp(0.5 * (lo + hi)))


def fit_calibration(residuals: np.ndarray, cov: np.ndarray) -> CovarianceCalibration:
    """The calibration of raw covariances ``cov`` (n, 2, 2) from held-out residuals
    (n, 2) = estimate − truth; identity when there are fewer than 10 finite residuals, a
    shrunk scale alone below ``TWO_PARAMETERS_FROM``."""
    r = np.asarray(residuals, dtype=float)
    c = np.asarray(cov, dtype=float)
    ok = np.isfinite(r).all(axis=1) & np.isfinite(c).all(axis=(1, 2))
    r, c = r[ok], c[ok]
    if len(r) < 10:
        return IDENTITY
    if len(r) < TWO_PARAMETERS_FROM:
        s = _scale_for_mean(r, c, 0.0)
        if s is None:
            return IDENTITY
        return CovarianceCalibration(float(np.exp(len(r) / (len(r) + SHRINK_N) * np.log(s))), 0.0)
    best: tuple[float, CovarianceCalibration] | None = None
    for floor_m in FLOOR_GRID_M:
        s = _scale_for_mean(r, c, floor_m)
        if s is None:
            continue
        cal = CovarianceCalibration(s, floor_m)
        score = abs(np.log(max(float(np.median(nis(r, cal.apply(c)))), 1e-12) / CHI2_2_MEDIAN))
        if best is None or score < best[0] - 1e-9:
            best = (score, cal)
    return IDENTITY if best is None else best[1]


def whiten(residuals: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """L⁻¹r per row (LLᵀ = C, Cholesky): residuals (n, 2), covariances (n, 2, 2); |L⁻¹r|² is the NIS."""
    return np.linalg.solve(np.linalg.cholesky(np.asarray(cov, float)), np.asarray(residuals, float)[..., None])[..., 0]


def measure_walk_share(residuals: np.ndarray, cov: np.ndarray, groups: np.ndarray, xy: np.ndarray,
                       min_distance_m: float = WALK_SHARE_MIN_M) -> float | None:
    """The share ρ of a fix's (calibrated) covariance ``cov`` that the fixes of one group (a walk,
    a phone) have in common. Whitened residuals wᵢ = Lᵢ⁻¹rᵢ (LLᵀ = Cᵢ, each clipped at |w|² ≤
    ``NIS_CLIP``); per group g, over its ordered pairs at least ``min_distance_m`` apart (true
    positions ``xy``), c_g = mean wᵢ·wⱼ and p_g = mean |wᵢ|²; ρ = mean c_g / mean p_g over the
    groups with at least ``WALK_SHARE_MIN_PAIRS`` such pairs, kept in [0, ``WALK_SHARE_MAX``]; None
    with fewer than ``WALK_SHARE_MIN_GROUPS`` of them. Each group weighs the same (as a new walk
    would): pooled over pairs, the longest walks decided alone (0.12–0.78 over the four MSFT fold
    maps); a ratio per group would be biased low (E[c/p] < E[c]/E[p])."""
    r = np.asarray(residuals, float)
    c = np.asarray(cov, float)
    ok = np.isfinite(r).all(axis=1) & np.isfinite(c).all(axis=(1, 2))
    w = whiten(r[ok], c[ok])
    n2 = np.einsum("ij,ij->i", w, w)
    w *= np.sqrt(np.minimum(1.0, NIS_CLIP / np.maximum(n2, 1e-300)))[:, None]
    g, p = np.asarray(groups).astype(str)[ok], np.asarray(xy, float)[ok]
    cross, power = [], []
    for name in np.unique(g):
        i = np.flatnonzero(g == name)
        far = np.hypot(*(p[i, None, :] - p[None, i, :]).transpose(2, 0, 1)) >= min_distance_m
        k = int(far.sum())
        if k >= WALK_SHARE_MIN_PAIRS:
            wi = w[i]
            cross.append(float(np.sum((wi @ wi.T)[far])) / k)
            power.append(float(np.sum(far, axis=1) @ np.einsum("ij,ij->i", wi, wi)) / k)
    if len(cross) < WALK_SHARE_MIN_GROUPS or sum(power) <= 0:
        return None
    return float(np.clip(np.mean(cross) / np.mean(power), 0.0, WALK_SHARE_MAX))
