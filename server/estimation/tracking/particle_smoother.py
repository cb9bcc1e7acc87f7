"""Fixed-lag path-space smoothing of a particle filter's estimates (Kitagawa 1996; Doucet &
Johansen 2009, §4.1).

A particle's ancestors are a path through the walk: the particles that survive later
measurements are the ones whose past fitted them, so the weighted positions, at an earlier
estimate, of the ancestors of a later cloud's particles are that estimate smoothed by the
measurements between them. ``PathSmoother`` follows a ``ParticleFilterXYTracker`` (the seed
form and the self-calibrating PF) estimate by estimate: it keeps the clouds of the last ``lag``
estimates and, for each current particle, the row of its ancestor in each (re-indexed at every
resampling through the tracker's ``take_lineage``), and gives each estimate the weighted mean and covariance of those
positions under the weights of the cloud ``lag`` estimates later (the last cloud's, for the
walk's last ``lag`` estimates). A cloud drawn anew (a floor change, a reset) ends every path: the
estimates before it are smoothed with the cloud before it.

Bounded memory (``lag`` × particles × (2 floats + a row)) and one pass, so it serves a replay of a whole
session; a longer lag smooths more but the paths coalesce onto fewer ancestors the further back
they reach (path degeneracy), which narrows the covariance (``PathSmoother`` widens it back by
the ancestors' effective count): ``DEFAULT_LAG`` is where both were measured.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from server.estimation.floorplan import Walkable
from server.estimation.tracking.base import symmetric
from server.estimation.tracking.pf import ParticleFilterXYTracker, weighted_covariance

#: estimates a smoothed estimate looks ahead: chosen among 20, 40 and 80 on the simulator's tune
#: (with and without the loop's plan) and stress (with it) splits, by the mean of smoothed / live
#: error (0.918 / 0.883 / 0.872) with the smoothed NEES ≤ 4 in each (docs/tracking-design.md,
#: "The particle smoother")
DEFAULT_LAG = 80


@dataclass(frozen=True)
class Smoothed:
    """One smoothed estimate: position (inside its floor's walkable area where it has one) and covariance."""

    mean: np.ndarray
    covariance: np.ndarray


@dataclass
class _Pending:
    """An estimate waiting for its lag: its cloud's positions, for each current particle the row of
    its ancestor there, the cloud's own covariance, what the fixes' shared error adds to it
    (``shared_error``) and the floor's walkable area."""

    positions: np.ndarray
    ancestors: np.ndarray
    covariance: np.ndarray
    excess: np.ndarray | None
    walkable: Walkable | None


class PathSmoother:
    """Observe the tracker after each of its estimates (``observe``); ``finish`` gives every
    observed estimate's smoothed position, in order.

    The covariance: the ancestors' weighted spread understates the smoothed one when the paths
    have coalesced onto few ancestors (their effective count n_a = 1/Σ aₖ², aₖ the current weight
    that descends from ancestor k), so each ancestor is taken as a kernel, as in the regularised PF:
    the ancestors' spread + h²·(the cloud's own covariance at that estimate), h² = n_a^(−1/3)
    (Silverman's bandwidth for 2-D, the one ``pf._spread_survivors`` uses), and never wider than
    the live covariance in any direction (``no_wider``: later measurements add information); one
    ancestor left gives the live covariance back."""

    def __init__(self, lag: int = DEFAULT_LAG):
        if lag < 0:
            raise ValueError("lag must be at least 0")
        self.lag = int(lag)
        self._pending: list[_Pending] = []
        self._n = 0  # particles in the last observed cloud
        self._weights: np.ndarray | None = None  # the last observed cloud's weights
        self._done: list[Smoothed] = []

    def observe(self, tracker: ParticleFilterXYTracker, covariance: np.ndarray,
                excess: np.ndarray | None = None) -> None:
        """The tracker has just made an estimate, of the cloud's ``covariance`` (and the session's
        ``excess`` for the fixes' shared error, which later fixes share too, so it stays in the
        smoothed covariance): trace the pending estimates' ancestors through its resamplings since
        the last one, add its cloud, and smooth the estimate ``lag`` back."""
        rows = tracker.take_lineage()
        if self._pending:
            if rows.min() < 0 or rows.max() >= self._n:  # drawn anew: the paths end with the cloud before
                self._emit(len(self._pending))
            elif len(rows) != self._n or not np.array_equal(rows, np.arange(self._n)):
                for p in self._pending:
                    p.ancestors = p.ancestors[rows]
        positions = np.array(tracker.particles[:, :2], float)
        self._n = len(positions)
        self._pending.append(_Pending(positions, np.arange(self._n), covariance,
                                      excess if excess is not None and excess.any() else None, tracker.walkable))
        self._weights = np.array(tracker.weights, float)
        if len(self._pending) > self.lag:
            self._emit(len(self._pending) - self.lag)

    def finish(self) -> list[Smoothed]:
        """Every observed estimate smoothed (the last ``lag`` by the last cloud), oldest first."""
        self._emit(len(self._pending))
        return list(self._done)

    def _emit(self, k: int) -> None:
        """Smooth the ``k`` oldest pending estimates with the last observed cloud's weights."""
        w = self._weights
        assert w is not None
        for p in self._pending[:k]:
            points = p.positions[p.ancestors]
            mean = w @ points
            share = np.bincount(p.ancestors, weights=w, minlength=len(p.positions))
            h2 = float(share @ share) ** (1.0 / 3.0)  # (1/n_a)^(1/3)
            cov = no_wider(weighted_covariance(points, w) + h2 * p.covariance, p.covariance)
            if p.excess is not None:
                cov = cov + p.excess
            if p.walkable is not None:
                mean = p.walkable.nearest_inside(mean)[0]
            self._done.append(Smoothed(np.asarray(mean, float), cov))
        del self._pending[:k]


def no_wider(cov: np.ndarray, bound: np.ndarray) -> np.ndarray:
    """``cov`` shrunk, direction by direction, to be no wider than ``bound``: with L Lᵀ = bound
    and L⁻¹ cov L⁻ᵀ = V Λ Vᵀ, L V min(Λ, 1) Vᵀ Lᵀ."""
    L = np.linalg.cholesky(symmetric(bound) + 1e-9 * np.eye(len(bound)))
    A = np.linalg.solve(L, np.linalg.solve(L, symmetric(cov)).T)
    lam, V = np.linalg.eigh(symmetric(A))
    return symmetric(L @ (V * np.minimum(lam, 1.0)) @ V.T @ L.T) + 1e-9 * np.eye(len(bound))

